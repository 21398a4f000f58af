"""What every test module shares: the ``slow`` and ``gpu`` markers skip themselves (``RUN_SLOW=1`` runs
slow tests; gpu tests need a CUDA device), and the ``mi`` fixture is Mitsuba with the project's variant.

Tiny scenes and temporary stores are not fixtures here: each module builds its own from helpers
(``test_stores_synthetic.synthetic_frame``, ``test_training.make_store``, pytest's ``tmp_path``)."""
from __future__ import annotations

import os
import subprocess

import pytest


def pytest_collection_modifyitems(config, items):
    run_slow = os.environ.get("RUN_SLOW") == "1"
    try:
        import torch
        has_gpu = torch.cuda.is_available()
    except Exception:  # pragma: no cover
        has_gpu = False
    for item in items:             # markers, not keywords: a parameter named "gpu" is a keyword too
        if item.get_closest_marker("slow") and not run_slow:
            item.add_marker(pytest.mark.skip(reason="slow: set RUN_SLOW=1"))
        if item.get_closest_marker("gpu") and not has_gpu:
            item.add_marker(pytest.mark.skip(reason="needs a CUDA device"))


@pytest.fixture(scope="session")
def mi():
    """Mitsuba with the project's variant (``core.variant``: llvm_ad_rgb without a GPU), drjit's
    thread pool left at its default."""
    from core.variant import mitsuba
    return mitsuba()


@pytest.fixture(scope="session")
def _suite_folder(tmp_path_factory):
    from scene_gen.real_scenes import write_suite
    root = tmp_path_factory.mktemp("data")
    write_suite(root / "real-scenes")
    return root


@pytest.fixture
def real_scene_data(_suite_folder, monkeypatch):
    """``DENOISE_DATA`` set to a folder holding the real-scene suite's files, where ``configs/real-scenes.yaml``
    names them (``make real-scenes`` writes them there; a fresh clone has none)."""
    monkeypatch.setenv("DENOISE_DATA", str(_suite_folder))
    return _suite_folder


@pytest.fixture(autouse=True)
def _flush_denormals_stays_in_its_test():
    """``training`` flushes float32 denormals to zero for speed (``torch.set_flush_denormal``), a
    process-wide setting; undo it after each test so later ones (hypothesis' subnormal floats) see IEEE
    arithmetic whatever ran before."""
    yield
    import sys
    torch = sys.modules.get("torch")
    if torch is not None:
        torch.set_flush_denormal(False)


@pytest.fixture
def small_disk(tmp_path):
    """A 1 MiB tmpfs (root only; skipped otherwise), unmounted afterwards."""
    d = tmp_path / "disk"
    d.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(d)], capture_output=True, text=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs to fill up (needs root): {r.stderr.strip()}")
    try:
        yield d
    finally:
        subprocess.run(["umount", "-l", str(d)], capture_output=True)
