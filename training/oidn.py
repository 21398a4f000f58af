"""Intel Open Image Denoise baseline (PyPI ``pyoidn``), given albedo and normal guides."""
from __future__ import annotations

import numpy as np


def oidn_denoise(color: np.ndarray, albedo: np.ndarray | None = None, normal: np.ndarray | None = None) -> np.ndarray:
    """Denoise HDR linear ``color (float32, HW3)`` with optional ``albedo`` (HW3, in [0, 1]) and
    ``normal`` (HW3, in [-1, 1]); returns float32 HW3. OIDN's RT filter, HDR mode, high quality."""
    import pyoidn

    c = np.ascontiguousarray(np.clip(np.nan_to_num(color, nan=0.0, posinf=0.0), 0.0, None), dtype=np.float32)
    a = None if albedo is None else np.ascontiguousarray(np.clip(albedo, 0.0, 1.0), dtype=np.float32)
    n = None if normal is None else np.ascontiguousarray(np.clip(normal, -1.0, 1.0), dtype=np.float32)
    return np.asarray(pyoidn.denoise(c, a, n, hdr=True), dtype=np.float32)


def oidn_denoise_tensor(color, albedo=None, normal=None):
    """OIDN on torch tensors (HW3 float32), on the tensors' device: OIDN's CUDA device for CUDA tensors
    (``pyoidn``'s wheel carries ``libOpenImageDenoise_device_cuda``), its CPU device otherwise. Inputs
    are cleaned as in :func:`oidn_denoise`; returns a tensor on the same device."""
    import pyoidn
    import torch

    c = torch.nan_to_num(color.float(), nan=0.0, posinf=0.0).clamp_min(0.0).contiguous()
    a = None if albedo is None else albedo.float().clamp(0.0, 1.0).contiguous()
    n = None if normal is None else normal.float().clamp(-1.0, 1.0).contiguous()
    return pyoidn.denoise(c, a, n, hdr=True)
