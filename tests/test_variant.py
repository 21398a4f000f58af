"""Variant selection: a working llvm_ad_rgb here, and clear errors (not LLVM crash dumps) otherwise."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

SNIPPET = ("from core.variant import mitsuba\n"
           "from core.errors import VariantError\n"
           "try:\n    mitsuba()\nexcept VariantError as e:\n    print('VariantError:', e); raise SystemExit(3)\n"
           "print('ok')\n")


def _run(env_update: dict) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k not in ("DRJIT_LIBLLVM_PATH", "MI_VARIANT")}
    env.update(env_update)
    return subprocess.run([sys.executable, "-c", SNIPPET], env=env, capture_output=True, text=True, timeout=300)


def test_default_variant_is_llvm_on_cpu(mi):
    import drjit as dr
    assert mi.variant() in ("llvm_ad_rgb", "cuda_ad_rgb")
    img = mi.render(mi.load_dict(mi.cornell_box()), spp=1)
    assert dr.all(dr.isfinite(img), axis=None)


def test_missing_libllvm_path_is_a_clear_error():
    r = _run({"DRJIT_LIBLLVM_PATH": "/nonexistent/libLLVM.so.19.1", "DENOISE_FORCE_CPU": "1"})
    assert r.returncode == 3, r.stderr
    assert "DRJIT_LIBLLVM_PATH" in r.stdout and "/nonexistent/libLLVM.so.19.1" in r.stdout


def test_broken_libllvm_gives_variant_error_not_crash(tmp_path):
    fake = tmp_path / "libLLVM.so.19.1"
    fake.write_bytes(b"this is not a shared library")
    r = _run({"DRJIT_LIBLLVM_PATH": str(fake), "DENOISE_FORCE_CPU": "1", "XDG_CACHE_HOME": str(tmp_path / "cache")})
    assert r.returncode == 3, (r.stdout, r.stderr)
    assert "cannot start" in r.stdout and "libLLVM" in r.stdout


def test_unknown_variant_is_refused():
    r = _run({"MI_VARIANT": "llvm_ad_hyperspectral", "DENOISE_FORCE_CPU": "1"})
    assert r.returncode == 3
    assert "unknown Mitsuba variant" in r.stdout and "llvm_ad_rgb" in r.stdout


def test_scene_gen_renders_without_importing_pipeline():
    """The variant is a leaf (core.variant): scene generation and its Mitsuba scenes need no
    pipeline module (pipeline imports scene_gen, never the other way)."""
    code = ("import sys\n"
            "from scene_gen.sampling import sample_scene\n"
            "from scene_gen import to_mitsuba\n"
            "from core.variant import mitsuba\n"
            "spec = sample_scene(2, 'outdoor', res=8)\n"
            "mi = mitsuba()\n"
            "img = mi.render(to_mitsuba.load(spec, 0, 8, merge=True), spp=1)\n"
            "import scene_gen.__main__\n"
            "print(sorted(m for m in sys.modules if m.split('.')[0] == 'pipeline'))\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                       cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.strip().splitlines()[-1] == "[]"


def test_the_variant_is_chosen_in_core_alone():
    """One module chooses the variant (core.variant); its error is a project error and a RuntimeError."""
    import core.variant
    from core.errors import ProjectError, VariantError
    assert core.variant.VariantError is VariantError
    assert issubclass(VariantError, ProjectError) and issubclass(VariantError, RuntimeError)
    root = Path(__file__).resolve().parent.parent
    assert not (root / "pipeline" / "variant.py").exists() and not (root / "scene_gen" / "variant.py").exists()