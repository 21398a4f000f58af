"""scripts/device_check.py: what travels to a GPU machine fits, the slimmed Mitsuba wheel still renders
every scene of the check (tried here with this machine's Python and the LLVM variant), and the parts
of the check that need no GPU agree with the tests' own oracles."""
from __future__ import annotations

import json
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent
SCRIPT = ROOT / "scripts" / "device_check.py"
sys.path.insert(0, str(SCRIPT.parent))
import device_check as dc  # noqa: E402


def test_dry_run_prints_the_plan_and_the_carried_bytes_that_fit():
    r = subprocess.run([sys.executable, str(SCRIPT), "--dry-run"], cwd=ROOT, capture_output=True, text=True,
                       timeout=120)
    res = json.loads(r.stdout.strip().splitlines()[-1])
    tree = sum(v for k, v in dc.carried_files().items() if not k.startswith("build/"))
    assert res["carried_bytes"] >= tree > 100_000 and res["limit_bytes"] == 64 * 2 ** 20
    assert res["plan"] == ["setup", "render", "training", "inference", "ddp"]
    for name in res["plan"]:
        assert r.stdout.startswith(name) or f"\n{name}" in r.stdout
    assert r.returncode == (0 if res["fits"] else 1) and res["fits"] == (res["carried_bytes"] <= 64 * 2 ** 20)


def _source_wheels(tmp_path: Path) -> tuple[Path, Path] | None:
    """The Mitsuba and drjit wheels of this machine's Python (the versions installed), from pip's index."""
    from importlib.metadata import version
    r = subprocess.run([sys.executable, "-m", "pip", "download", "--no-deps", "--only-binary=:all:", "-q",
                        "-d", str(tmp_path), f"mitsuba=={version('mitsuba')}", f"drjit=={version('drjit')}"],
                       capture_output=True, text=True, timeout=600)
    mi, dr = list(tmp_path.glob("mitsuba-*.whl")), list(tmp_path.glob("drjit-*.whl"))
    return (mi[0], dr[0]) if r.returncode == 0 and mi and dr else None


@pytest.fixture(scope="module")
def slim(tmp_path_factory):
    d = tmp_path_factory.mktemp("wheels")
    found = _source_wheels(d)
    if found is None:
        pytest.skip("pip cannot download the mitsuba and drjit wheels here (no package index)")
    src, drjit = found
    plugins = dc.used_plugins()
    out = d / "slim"
    out.mkdir()
    return src, dc.slim_mitsuba(src, out, plugins), plugins, drjit


def test_the_slim_mitsuba_wheel_keeps_what_the_scenes_load_and_fits(slim):
    src, wheel, plugins, _ = slim
    names = zipfile.ZipFile(wheel).namelist()
    kept_plugins = {Path(n).stem for n in names if n.startswith("mitsuba/plugins/")}
    assert kept_plugins == plugins and {"path", "hdrfilm", "perspective"} <= plugins
    for v in dc.VARIANTS:
        assert any(n.startswith(f"mitsuba/{v}.cpython-") for n in names), v
    assert not any("spectral" in n and n.endswith(".so") and "/plugins/" not in n for n in names)
    assert not any(n.startswith("mitsuba/include/") for n in names)
    record = next(n for n in names if n.endswith("dist-info/RECORD"))
    listed = {ln.split(",")[0] for ln in zipfile.ZipFile(wheel).read(record).decode().splitlines() if ln}
    assert listed == set(names)
    assert wheel.stat().st_size < 0.65 * src.stat().st_size
    # with drjit's wheel (5 MB) and the checkout, what travels stays within 64 MiB
    tree = sum(v for k, v in dc.carried_files().items() if not k.startswith("build/"))
    assert wheel.stat().st_size + 6 * 2 ** 20 + tree < dc.CARRY_LIMIT


def test_the_slim_wheel_renders_every_scene_of_the_check(slim, tmp_path):
    """Installed with drjit into a folder of their own, first on the path (as the check installs them
    there), it renders the check's scenes (LLVM variant)."""
    _, wheel, _, drjit = slim
    site = tmp_path / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "--no-index", "--no-deps", "-q", "--target", str(site),
                    str(wheel), str(drjit)], check=True, timeout=300)
    code = ("import sys; sys.path.insert(0, %r); import mitsuba; assert mitsuba.__file__.startswith(%r), "
            "mitsuba.__file__; sys.path.insert(0, %r); import device_check as d; d._render_all_scenes(); "
            "e = d.estimate(16); print(float(e['mean'].mean()))" % (str(site), str(site), str(SCRIPT.parent)))
    env = {"PYTHONPATH": str(ROOT), "MI_VARIANT": "llvm_ad_rgb", "PATH": "/usr/bin:/bin",
           "HOME": str(tmp_path)}
    import os
    for k in ("DRJIT_LIBLLVM_PATH",):
        if os.environ.get(k):
            env[k] = os.environ[k]
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=ROOT, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    assert float(r.stdout.strip().splitlines()[-1]) > 0


def test_the_agreement_test_tells_agreeing_estimates_from_biased_ones():
    rng = np.random.default_rng(0)
    truth = rng.random((32, 32, 3)) + 0.5
    var = np.full_like(truth, 1e-3)

    def est(bias=0.0):
        return {"mean": truth + bias + rng.normal(0, np.sqrt(var)), "var": var}
    assert dc.zmax(est(), est()) < 5
    assert dc.zmax(est(0.05), est()) > 5


def test_every_part_of_the_check_runs_here_at_toy_sizes(tmp_path):
    """``--smoke``: the GPU run's code on this CPU (LLVM for CUDA, gloo for nccl, toy sizes): one JSON
    with every part and no error, each figure a positive number."""
    out = tmp_path / "check.json"
    r = subprocess.run([sys.executable, str(SCRIPT), "--smoke", "--out", str(out)], cwd=ROOT, capture_output=True,
                       text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    res = json.loads(out.read_text())
    assert json.loads(r.stdout[r.stdout.index("{"):]) == res
    for part in ("setup", "render", "training", "inference", "ddp"):
        assert part in res and "error" not in res[part], (part, res.get(part))
    assert res["render"]["llvm_ad_rgb"]["generated"]["input_loop"] > 0 and res["render"]["agreement"]["z_max"] < 5
    assert set(res["training"]) == set(dc.TRAINING)
    for name, row in res["training"].items():
        assert row["fp32"]["steps_per_s"] > 0 and row["bf16"]["steps_per_s"] > 0, name
    from training.models import names
    assert set(names()) <= set(res["inference"])
    assert all(v > 0 for name in names() for v in res["inference"][name].values()), res["inference"]
    assert res["ddp"]["backend"] == "gloo" and np.isfinite(res["ddp"]["loss"])
    assert res["carried_bytes"] > 0 and res["total_seconds"] < 600


_CLOSURE = r"""
import contextlib, io, json, runpy, sys, importlib.metadata as md
sys.argv = ["device_check.py", "--render-child", "--res", "16"]
with contextlib.redirect_stdout(io.StringIO()):
    try:
        runpy.run_path("scripts/device_check.py", run_name="__main__")
    except SystemExit:
        pass
    sys.path.insert(0, "scripts")
    import device_check as dc
    dc.RUN.update(dc.SMOKE, sizes={"a": (16, 16)})
    dc.part_training({}, lambda: 1e9)
    dc.part_inference({}, lambda: 1e9)
    dc.part_ddp({}, lambda: 1e9)
    dc.estimate(8)
pd = md.packages_distributions()
print(json.dumps(sorted({d for t in {m.split(".")[0] for m in sys.modules} for d in pd.get(t, [])})))
"""


def _requirements(dist: str, seen: set) -> set:
    """``dist`` and everything it requires, recursively (as installed here)."""
    import importlib.metadata as md
    import re
    if dist.lower() in seen:
        return seen
    seen.add(dist.lower())
    try:
        reqs = md.requires(dist) or []
    except md.PackageNotFoundError:
        return seen
    for r in reqs:
        if "extra ==" not in r:
            _requirements(re.split(r"[ ;<>=!~\[]", r, maxsplit=1)[0], seen)
    return seen


def test_the_check_imports_only_what_travels_or_the_gpu_machine_has():
    """Run here, every part of the check imports only the carried distributions, its own checkout and
    what it takes from the machine (torch with its requirements, numpy, scipy, tqdm, pillow): pymeshlab
    stays home."""
    r = subprocess.run([sys.executable, "-c", _CLOSURE], cwd=ROOT, capture_output=True, text=True, timeout=600,
                       env={**__import__("os").environ, "PYTHONPATH": str(ROOT), "MI_VARIANT": "llvm_ad_rgb"})
    assert r.returncode == 0, r.stderr[-3000:]
    def norm(names):
        return {n.lower().replace("_", "-") for n in names}
    used = norm(json.loads(r.stdout.strip().splitlines()[-1]))
    allowed = norm(dc.CARRIED) | {"denoise-datagen", "numpy", "scipy", "tqdm", "pillow"}
    allowed |= norm(_requirements("torch", set()))
    allowed |= {"setuptools", "charset-normalizer", "rtree"}     # torch's on Python 3.12; optional ones
    assert "pymeshlab" not in used and used <= allowed, sorted(used - allowed)
