"""Variant selection: a working llvm_ad_rgb here, and clear errors (not LLVM crash dumps) otherwise."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path


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
            "import scene_gen.commands\n"
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

# ---- GPUs: detected in core.variant alone ----------------------------------------------------------------
def _fake_nvidia_smi(tmp_path, monkeypatch, n: int) -> None:
    """An ``nvidia-smi`` on PATH that lists ``n`` GPUs, as the driver's does."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    lines = "\\n".join(f"GPU {i}: NVIDIA H200 (UUID: GPU-{i:08d})" for i in range(n))
    (bin_dir / "nvidia-smi").write_text(f'#!/bin/sh\n[ "$1" = "-L" ] && printf "{lines}\\n"\n')
    (bin_dir / "nvidia-smi").chmod(0o755)
    monkeypatch.setenv("PATH", f"{bin_dir}:{os.environ['PATH']}")
    monkeypatch.delenv("DENOISE_FORCE_CPU", raising=False)


def test_visible_gpus_are_nvidia_smis_within_cuda_visible_devices(tmp_path, monkeypatch):
    from core.variant import visible_gpus
    monkeypatch.delenv("CUDA_VISIBLE_DEVICES", raising=False)
    assert visible_gpus() == [] or visible_gpus()                  # this machine: whatever it has
    _fake_nvidia_smi(tmp_path, monkeypatch, 3)
    assert visible_gpus() == ["0", "1", "2"]
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "2,0")
    assert visible_gpus() == ["2", "0"]
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "-1")
    assert visible_gpus() == []
    monkeypatch.setenv("DENOISE_FORCE_CPU", "1")
    monkeypatch.delenv("CUDA_VISIBLE_DEVICES")
    assert visible_gpus() == []


def test_the_variant_follows_the_visible_gpus(tmp_path, monkeypatch):
    from core.variant import choose_variant
    monkeypatch.delenv("MI_VARIANT", raising=False)
    monkeypatch.delenv("CUDA_VISIBLE_DEVICES", raising=False)
    _fake_nvidia_smi(tmp_path, monkeypatch, 2)
    assert choose_variant() == "cuda_ad_rgb"
    assert choose_variant("llvm_ad_rgb") == "llvm_ad_rgb"
    monkeypatch.setenv("DENOISE_FORCE_CPU", "1")
    assert choose_variant() == "llvm_ad_rgb"
    monkeypatch.delenv("DENOISE_FORCE_CPU")
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "-1")                # the driver is there, no device for us
    assert choose_variant() == "llvm_ad_rgb"


def test_only_core_variant_runs_nvidia_smi():
    """The packages detect GPUs through core.variant.visible_gpus: no other module runs nvidia-smi."""
    import ast
    root = Path(__file__).resolve().parent.parent
    found = sorted(str(p.relative_to(root)) for pkg in ("core", "scene_gen", "stores", "pipeline", "training", "studies")
                   for p in (root / pkg).rglob("*.py")
                   if any(isinstance(n, ast.Constant) and n.value == "nvidia-smi" for n in ast.walk(ast.parse(p.read_text()))))
    assert found == ["core/variant.py"]


def test_a_started_variant_is_returned_without_asking_for_the_gpus_again(mi, monkeypatch):
    """After the first call, ``mitsuba()`` runs no subprocess: scene_gen.to_mitsuba asks for the module on every
    ``set_time`` (16 a moving reference), and each ``nvidia-smi -L`` costs a GPU machine tens of milliseconds."""
    import subprocess

    import core.variant
    import pipeline.render as R
    from scene_gen import sampling

    def no_subprocess(*a, **k):
        raise AssertionError(f"mitsuba() ran a subprocess after the variant was started: {a}")
    monkeypatch.delenv("MI_VARIANT", raising=False)
    monkeypatch.setattr(subprocess, "run", no_subprocess)
    assert core.variant.mitsuba() is mi and core.variant.mitsuba(threads=0) is mi
    spec = sampling.sample_scene(0, "outdoor", num_frames=1, res=16)
    assert spec.has_motion                  # a moving scene: every set_time asks for the module
    fs = R.FrameScene(spec, 0, R.RenderConfig(res=(16, 16), spp=1, layer_levels=1, ref_spp=8, ref_passes=2,
                                              ref_min_passes=2))
    fs.set_time(0.5)
    fs.set_time(0.0)
