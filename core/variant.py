"""Choose and start the Mitsuba variant in one place (in ``core``: ``scene_gen``'s previews and
``pipeline``'s renderer both use it).

``cuda_ad_rgb`` when a CUDA device works, else ``llvm_ad_rgb``. drjit's LLVM backend needs a
shared libLLVM >= 16 (the Debian libLLVM-15 aborts inside LLVM on some CPUs), so the library is
located *before* mitsuba is imported and ``DRJIT_LIBLLVM_PATH`` is set for drjit.

Every module that renders calls :func:`mitsuba` instead of ``import mitsuba`` directly.

``DENOISE_LLVM_TARGET=CPU:FEATURES:WIDTH`` (e.g. ``haswell:-avx512f,+avx2,+fma:8``) makes drjit's LLVM
backend generate code for another CPU (``jit_llvm_set_target``): how a machine with AVX-512 checks what
an AVX2-only machine computes (the pinned tests' tolerances, docs/throughput.md).
"""
from __future__ import annotations

import glob
import os
import subprocess
import sys
from pathlib import Path

from core.errors import VariantError

_LLVM_CANDIDATES = [
    f"{d}/{pat}"
    for v in (21, 20, 19, 18, 17, 16)
    for d in ("/usr/lib/x86_64-linux-gnu", "/usr/lib/aarch64-linux-gnu", "/usr/lib", "/usr/local/lib",
              f"/usr/lib/llvm-{v}/lib")
    for pat in (f"libLLVM.so.{v}.1", f"libLLVM-{v}.so", f"libLLVM.so.{v}")
]
_state: dict = {}


def find_libllvm() -> str | None:
    """Path of a shared libLLVM >= 16, honouring ``DRJIT_LIBLLVM_PATH`` and setup's ``.llvm-path``."""
    env = os.environ.get("DRJIT_LIBLLVM_PATH")
    if env:
        if not Path(env).is_file():
            raise VariantError(f"DRJIT_LIBLLVM_PATH={env!r} does not exist")
        return env
    stamp = Path(__file__).resolve().parent.parent / ".llvm-path"
    if stamp.is_file():
        p = stamp.read_text().strip()
        if p and Path(p).is_file():
            return p
    for pat in _LLVM_CANDIDATES:
        for p in glob.glob(pat):
            return p
    return None


def visible_gpus() -> list[str]:
    """The CUDA devices this process may use: ``nvidia-smi -L``'s, within ``CUDA_VISIBLE_DEVICES`` when
    it is set (its entries, indices or UUIDs, in its order); [] without a working driver or with
    ``DENOISE_FORCE_CPU``. The one place GPUs are detected: the variant (:func:`cuda_available`) and
    ``pipeline.cluster``'s one worker per GPU both ask it."""
    if os.environ.get("DENOISE_FORCE_CPU"):
        return []
    try:
        out = subprocess.run(["nvidia-smi", "-L"], capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.TimeoutExpired):
        return []
    listed = [ln for ln in out.stdout.splitlines() if ln.startswith("GPU ")] if out.returncode == 0 else []
    env = os.environ.get("CUDA_VISIBLE_DEVICES")
    if env is None:
        return [str(i) for i in range(len(listed))]
    return [d.strip() for d in env.split(",") if d.strip() and d.strip() != "-1"][:len(listed)]


def cuda_available() -> bool:
    """Whether this process sees a CUDA device (:func:`visible_gpus`)."""
    return bool(visible_gpus())


def _probe(variant: str, env: dict) -> str | None:
    """Start the variant in a child process so an LLVM abort cannot kill us; return an error or None."""
    code = ("import mitsuba as mi, drjit as dr; mi.set_variant(%r); "
            "s = mi.load_dict({'type':'scene','integrator':{'type':'path'},"
            "'sensor':{'type':'perspective','film':{'type':'hdrfilm','width':4,'height':4}},"
            "'e':{'type':'constant'}}); img = mi.render(s, spp=1); print(dr.mean(img, axis=None))" % variant)
    try:
        r = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, timeout=300)
    except subprocess.TimeoutExpired:
        return "timed out after 300 s"
    if r.returncode != 0:
        tail = (r.stderr or b"").decode(errors="replace").strip().splitlines()[-3:]
        return f"exit code {r.returncode}: {' | '.join(tail)}"
    return None


def choose_variant(preferred: str | None = None, probe: bool | None = None) -> str:
    """Return the variant to use: ``preferred`` (or ``$MI_VARIANT``), else cuda_ad_rgb / llvm_ad_rgb."""
    preferred = preferred or os.environ.get("MI_VARIANT")
    if preferred:
        return preferred
    return "cuda_ad_rgb" if cuda_available() else "llvm_ad_rgb"


def mitsuba(variant: str | None = None, threads: int | None = None):
    """Import mitsuba with a working variant set; returns the module. Idempotent and cheap after the first call.

    Raises :class:`VariantError` with a precise message when the variant cannot start (instead of an
    LLVM crash dump): a missing libLLVM names the Debian package and ``DRJIT_LIBLLVM_PATH``.
    """
    if variant is None and not os.environ.get("MI_VARIANT") and "variant" in _state:
        # The variant this process started: asking for the GPUs again would run nvidia-smi on every call
        # (scene_gen.to_mitsuba calls this on every set_time, 16 times a moving reference).
        variant = _state["variant"]
    variant = choose_variant(variant)
    if _state.get("variant") == variant:
        mi = _state["mi"]
        if threads is not None:
            _set_threads(threads)
        return mi
    _check_known(variant)
    if variant.startswith("llvm"):
        lib = find_libllvm()
        if lib is None:
            raise VariantError(
                "Mitsuba's LLVM variant needs a shared libLLVM >= 16 and none was found. "
                "Install Debian's package 'libllvm19' (apt-get install libllvm19, or run `make setup` as root) "
                "or set DRJIT_LIBLLVM_PATH to a libLLVM.so of version >= 16.")
        os.environ["DRJIT_LIBLLVM_PATH"] = lib
        if not _state.get(f"probed:{variant}:{lib}"):
            # Probe once per process in a child so a broken LLVM gives an error, not an abort.
            marker = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "denoise-datagen" / (
                f"variant-ok-{variant}-" + lib.replace("/", "_"))
            if not marker.exists():
                err = _probe(variant, dict(os.environ))
                if err:
                    raise VariantError(f"Mitsuba variant {variant!r} with libLLVM {lib} cannot start ({err}). "
                                       "drjit needs libLLVM >= 16; set DRJIT_LIBLLVM_PATH to another library.")
                marker.parent.mkdir(parents=True, exist_ok=True)
                marker.touch()
            _state[f"probed:{variant}:{lib}"] = True
    try:
        import mitsuba as mi
    except ImportError as e:  # pragma: no cover - setup installs it
        raise VariantError(f"mitsuba is not installed ({e}); run `make setup`") from e
    try:
        mi.set_variant(variant)
    except Exception as e:
        raise VariantError(f"Mitsuba variant {variant!r} cannot start: {e}. "
                           f"Available: {', '.join(mi.variants())}") from e
    _state.update(variant=variant, mi=mi)
    if variant.startswith("llvm") and os.environ.get("DENOISE_LLVM_TARGET"):
        _set_llvm_target(os.environ["DENOISE_LLVM_TARGET"])
    if threads is not None:
        _set_threads(threads)
    return mi


def _set_llvm_target(spec: str) -> None:
    """``CPU:FEATURES:WIDTH`` to drjit-core's ``jit_llvm_set_target`` (no Python binding: ctypes, by its
    C++ symbol); VariantError naming the setting when it does not parse or the library lacks it."""
    import ctypes

    import drjit as dr
    parts = spec.split(":")
    if len(parts) != 3 or not parts[2].isdigit() or int(parts[2]) not in (1, 2, 4, 8, 16, 32):
        raise VariantError(f"DENOISE_LLVM_TARGET must be CPU:FEATURES:WIDTH (a width of 1-32 lanes, a power of "
                           f"2), e.g. 'haswell:-avx512f,+avx2,+fma:8', got {spec!r}")
    try:
        fn = getattr(ctypes.CDLL(str(Path(dr.__file__).parent / "libdrjit-core.so")),
                     "_Z19jit_llvm_set_targetPKcS0_j")
    except (OSError, AttributeError) as e:
        raise VariantError(f"DENOISE_LLVM_TARGET is set but this drjit has no jit_llvm_set_target ({e})") from e
    fn.argtypes = [ctypes.c_char_p, ctypes.c_char_p, ctypes.c_uint32]
    fn(parts[0].encode(), parts[1].encode(), int(parts[2]))


def _check_known(variant: str) -> None:
    try:
        import mitsuba as mi_mod  # importing does not start a backend
    except ImportError as e:  # pragma: no cover - setup installs it
        raise VariantError(f"mitsuba is not installed ({e}); run `make setup`") from e
    if variant not in mi_mod.variants():
        raise VariantError(f"unknown Mitsuba variant {variant!r}; this build has: {', '.join(mi_mod.variants())}")


def _set_threads(n: int) -> None:
    import drjit as dr
    if n > 0 and dr.thread_count() != n:
        dr.set_thread_count(n)
