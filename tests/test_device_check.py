"""scripts/device_check.py: what travels to a GPU machine fits, the slimmed Mitsuba wheel still renders
every scene of the check (tried here with this machine's Python and the LLVM variant), the parts of the
check that need no GPU agree with the tests' own oracles, one model's failure stays that model's figure
and the JSON is written as the check goes, and the real job (dataset, validate, train, evaluate) runs
here end to end seeing only what the GPU machine has."""
from __future__ import annotations

import json
import subprocess
import sys
import time
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
    assert res["plan"] == ["setup", "realtime", "training", "e2e", "render", "inference", "ddp", "training-compiled"]
    for name in res["plan"]:
        assert r.stdout.startswith(name) or f"\n{name}" in r.stdout
    assert r.returncode == (0 if res["fits"] else 1) and res["fits"] == (res["carried_bytes"] <= 64 * 2 ** 20)
    # the two runs that fit 15 minutes of device time hold every part but the optional compiled training
    assert sorted(",".join(res["split"]).split(",")) == sorted(set(dc.PART_NAMES) - {"training-compiled"})


def test_parts_choose_what_one_run_does_in_the_checks_order():
    r = subprocess.run([sys.executable, str(SCRIPT), "--dry-run", "--parts", "e2e,realtime"], cwd=ROOT,
                       capture_output=True, text=True, timeout=120)
    assert json.loads(r.stdout.strip().splitlines()[-1])["plan"] == ["setup", "realtime", "e2e"]
    r = subprocess.run([sys.executable, str(SCRIPT), "--dry-run", "--e2e"], cwd=ROOT, capture_output=True,
                       text=True, timeout=120)
    assert json.loads(r.stdout.strip().splitlines()[-1])["plan"] == ["setup", "e2e"]
    r = subprocess.run([sys.executable, str(SCRIPT), "--dry-run", "--parts", "realtime,gpu"], cwd=ROOT,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "unknown part(s) gpu" in r.stderr and "realtime, training, e2e" in r.stderr


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
    # with drjit's and trimesh's wheels (5.5 MB), the pipeline's (16 MB: dask, distributed, zarr, numcodecs
    # 9 MB, ...) and the checkout, what travels stays within 64 MiB
    tree = sum(v for k, v in dc.carried_files().items() if not k.startswith("build/"))
    assert wheel.stat().st_size + 6 * 2 ** 20 + 16 * 2 ** 20 + tree < dc.CARRY_LIMIT


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


class _Fake:
    """A model as the check's parts see it (the timing functions are replaced)."""

    def __init__(self, name):
        self.name = name

    def input_spec(self):
        from types import SimpleNamespace
        return SimpleNamespace(default_spp=1)


def test_one_models_error_is_that_models_figure_and_each_model_is_saved(monkeypatch):
    """wskpn failing on the GPU erased the whole inference part's figures once: now its error is its own
    entry, the other models are timed, and the JSON is saved after each model."""
    import copy

    import training.bench as tb
    monkeypatch.setattr(dc, "RUN", dict(dc.SMOKE))
    monkeypatch.setattr(dc, "_models", lambda: (_Fake, None, lambda: ["nbg", "layer", "nppd", "pixelgather"]))

    def time_model(m, spp, size, repeats, dev, precision, compile=False):
        if m.name in ("wskpn", "nppd"):
            raise RuntimeError("Input type (torch.cuda.FloatTensor) and weight type (torch.FloatTensor) differ")
        return {"ms_per_frame": 1.0, "size": list(size)}
    monkeypatch.setattr(tb, "time_model", time_model)
    saved = []
    out: dict = {}
    dc.part_realtime({}, lambda: 1e9, out, lambda: saved.append(copy.deepcopy(out)))
    assert out["wskpn"]["bf16"]["error"].startswith("RuntimeError: Input type") and "ms_per_frame" not in out["wskpn"]["bf16"]
    for name in ("nbg", "temporal-small", "temporal"):
        assert out[name]["bf16"]["ms_per_frame"] == 1.0 and out[name]["fp32"]["ms_per_frame"] == 1.0
    assert len(saved) == 8 and list(saved[0]) == ["nbg"] and saved[-1] == out
    # the other models' inference: nppd's error beside the others' figures, out of time said as such
    out, t = {}, iter([1e9] * 6 + [0.0] * 100)
    dc.part_inference({}, lambda: next(t), out, lambda: None)
    assert list(out) == ["layer", "nppd", "pixelgather", "oidn"]
    assert out["layer"]["1080p_fp32"]["ms_per_frame"] == 1.0 and out["nppd"]["720p_bf16"]["error"].startswith("RuntimeError")
    assert out["nppd"]["720p_fp32"] == {"skipped": "out of time"} == out["pixelgather"]["1080p_bf16"]


def test_the_json_is_written_after_every_part_and_keeps_what_a_failed_part_measured(monkeypatch, tmp_path):
    path = tmp_path / "check.json"
    monkeypatch.setattr(dc, "part_setup", lambda state: {"gpu": None})

    def realtime(state, left, out, save):
        out["nbg"] = {"bf16": {"ms_per_frame": 3.1}}
        save()
        raise ValueError("the GPU fell off the bus")

    def training(state, left, out, save):
        on_disk = json.loads(path.read_text())          # written before this part started
        assert on_disk["realtime"] == {"nbg": {"bf16": {"ms_per_frame": 3.1}}, "error": "ValueError: the GPU fell off the bus"}
        while left() >= 10:                               # the last part starts with under 10 s left
            time.sleep(0.05)
        out["nbg"] = {"fp32": {"steps_per_s": 40.0}}
    monkeypatch.setattr(dc, "PART_FNS", {**dc.PART_FNS, "realtime": realtime, "training": training,
                                         "e2e": lambda *a: pytest.fail("ran past its budget")})
    res = dc.run_check(str(path), budget=12.0, parts=["realtime", "training", "e2e"])
    assert json.loads(path.read_text()) == json.loads(json.dumps(res, default=str))
    assert res["training"] == {"nbg": {"fp32": {"steps_per_s": 40.0}}} and res["e2e"] == {"skipped": "out of time"}
    assert set(res["seconds"]) == {"setup", "realtime", "training", "e2e"} and not (tmp_path / "check.json.part").exists()


def test_every_part_of_the_check_runs_here_at_toy_sizes(tmp_path):
    """``--smoke``: the GPU run's code on this CPU (LLVM for CUDA, gloo for nccl, toy sizes, the models at
    their test sizes): one JSON with every part but e2e (its own test) and no error, each figure a
    positive number."""
    out = tmp_path / "check.json"
    parts = [p for p in dc.PART_NAMES if p != "e2e"]
    r = subprocess.run([sys.executable, str(SCRIPT), "--smoke", "--parts", ",".join(parts), "--budget", "900",
                        "--out", str(out)], cwd=ROOT, capture_output=True, text=True, timeout=1200)
    assert r.returncode == 0, r.stderr[-3000:]
    res = json.loads(out.read_text())
    assert json.loads(r.stdout[r.stdout.index("{"):]) == res
    for part in ("setup", *parts):
        assert part in res and "error" not in res[part], (part, res.get(part))
    for name in dc.REALTIME:
        assert res["realtime"][name]["bf16"]["ms_per_frame"] > 0 and res["realtime"][name]["fp32"]["ms_per_frame"] > 0
    from training.bench import PAPER_TRAINING
    assert set(res["training"]) == set(PAPER_TRAINING)
    for name, row in res["training"].items():
        assert row["fp32"]["steps_per_s"] > 0 and row["bf16"]["steps_per_s"] > 0, name
    r = res["render"]["llvm_ad_rgb"]
    assert r["inputs_msamples_per_s"] > 0 and r["reference_msamples_per_s"] > 0 and r["cornell_msamples_per_s"] > 0
    assert res["render"]["agreement"]["z_max"] < 5
    from training.models import names
    assert set(names()) - set(dc.REALTIME) <= set(res["inference"])
    assert all(v["ms_per_frame"] > 0 for name in set(names()) - set(dc.REALTIME)
               for v in res["inference"][name].values()), res["inference"]
    assert res["ddp"]["backend"] == "gloo" and np.isfinite(res["ddp"]["loss"])
    assert "skipped" in res["training-compiled"]
    assert res["carried_bytes"] > 0 and res["total_seconds"] < 900


def _machine_env(tmp_path) -> dict:
    """An environment in which a Python process sees only the distributions the GPU machine has or
    receives (tests/gpu_machine/sitecustomize.py): pymeshlab, bokeh and the rest are not found."""
    import os
    allowed = set(dc._closure(dc.MACHINE_ROOTS)) | set(dc._closure(dc.PIPELINE_ROOTS)) | set(dc._closure(dc.CARRIED))
    allowed |= {"denoise-datagen", "pip"}
    assert "pymeshlab" not in allowed and "bokeh" not in allowed
    return {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT / "tests" / "gpu_machine"), str(ROOT)]),
            "DENOISE_TEST_ALLOWED_DISTS": ",".join(sorted(allowed)), "HOME": str(tmp_path)}


def test_the_real_job_runs_here_end_to_end_seeing_only_what_the_gpu_machine_has(tmp_path):
    """``--e2e --smoke``: configs/gpu-e2e.yaml at toy sizes rendered by a LocalCluster (LLVM), validated,
    nbg and layer trained for seconds and evaluated with the noisy input on the test split, every
    process seeing only what the GPU machine has or receives (no pymeshlab): the figures the GPU run
    prints, each of them there."""
    out = tmp_path / "e2e.json"
    env = _machine_env(tmp_path)
    r = subprocess.run([sys.executable, str(SCRIPT), "--e2e", "--smoke", "--out", str(out)], cwd=ROOT,
                       capture_output=True, text=True, timeout=600, env=env)
    assert r.returncode == 0, r.stderr[-3000:]
    res = json.loads(out.read_text())
    assert res["parts"] == ["e2e"] and "error" not in res["e2e"], res["e2e"]
    e = res["e2e"]
    ds = e["dataset"]
    assert ds["ok"] and ds["rendered"] == ds["frames"] == 4 and ds["frames_per_s"] > 0 and ds["failed"] == 0
    assert abs(sum(ds["share"].values()) - 1) < 1e-6 and ds["share"]["render"] > 0 and ds["share"]["write"] > 0
    assert e["validate"]["ok"] and e["validate"]["tail"][-1] == "OK"
    for model in ("nbg", "layer"):
        t = e["train"][model]
        assert t["rc"] == 0 and t["steps"] >= 2 and t["steps_per_s"] > 0 and 0 <= t["loader_wait_share"] <= 1, t
    for method in ("input", "nbg", "layer"):
        ev = e["evaluate"][method]
        assert ev["rc"] == 0 and ev["frames"] >= 1 and np.isfinite(ev["mean"]["relmse"]) and ev["mean"]["psnr"] > 0
    assert res["seconds"]["e2e"] < 300


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
    dc.RUN.update(dc.SMOKE, sizes={"720p": (16, 16), "1080p": (16, 16)})
    dc.part_realtime({}, lambda: 1e9, {}, lambda: None)
    dc.part_training({}, lambda: 1e9, {}, lambda: None)
    dc.part_inference({}, lambda: 1e9, {}, lambda: None)
    dc.part_ddp({}, lambda: 1e9, {}, lambda: None)
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
    """Run here, every part of the check's own process imports only the carried distributions, its own
    checkout and what it takes from the machine (torch with its requirements, numpy, scipy, tqdm,
    pillow, pyyaml): pymeshlab stays home. (The e2e part's processes: the test above.)"""
    r = subprocess.run([sys.executable, "-c", _CLOSURE], cwd=ROOT, capture_output=True, text=True, timeout=600,
                       env={**__import__("os").environ, "PYTHONPATH": str(ROOT), "MI_VARIANT": "llvm_ad_rgb"})
    assert r.returncode == 0, r.stderr[-3000:]
    def norm(names):
        return {n.lower().replace("_", "-") for n in names}
    used = norm(json.loads(r.stdout.strip().splitlines()[-1]))
    allowed = norm(dc.CARRIED) | {"denoise-datagen", "numpy", "scipy", "tqdm", "pillow", "pyyaml"}
    allowed |= norm(_requirements("torch", set()))
    allowed |= {"setuptools", "charset-normalizer", "rtree"}     # torch's on Python 3.12; optional ones
    assert "pymeshlab" not in used and used <= allowed, sorted(used - allowed)
