"""The command contract: train -> evaluate -> report on a tiny real store; OIDN baseline; figure 10; bench."""
from __future__ import annotations

import json
import time

import numpy as np
import pytest
from PIL import Image

from test_training import TINY, make_store
from training.__main__ import main


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    return make_store(tmp_path_factory.mktemp("store") / "tiny.zarr", per_split=(3, 1, 2))


def test_cli_train_evaluate_report(store, tmp_path):
    runs = tmp_path / "runs"
    for name, cfg in (("layer", TINY), ("layer-optimized", {**TINY, "kernel_size": 3, "unet_encoder": ((8,),) * 3, "unet_decoder": ((8,),) * 3})):
        rc = main(["train", "--model", name, "--store", store, "--steps", "2", "--crop", "16", "--batch", "2",
                   "--spp", "2", "--out", str(runs / name), "--model-cfg", json.dumps(cfg), "--no-progress",
                   "--val-every", "2", "--val-frames", "1"])
        assert rc == 0 and (runs / name / "checkpoint.pt").is_file() and (runs / name / "metrics.csv").is_file()

    out = tmp_path / "eval.json"
    assert main(["evaluate", "--checkpoint", str(runs / "layer" / "checkpoint.pt"), "--store", store,
                 "--out", str(out)]) == 0
    res = json.loads(out.read_text())
    assert res["method"] == "layer" and res["split"] == "test" and res["spp"] == 2 and len(res["frames"]) == 2
    for f in res["frames"]:
        assert {"relmse", "smape", "psnr", "ssim", "flip", "ms_per_megapixel"} <= set(f)
        assert f["ms_per_megapixel"] > 0 and 0 <= f["flip"] <= 1 and np.isfinite(f["relmse"])
    assert res["mean"]["relmse"] == pytest.approx(np.mean([f["relmse"] for f in res["frames"]]))
    from training.data import open_store
    from training.evaluate import frame_kinds
    st = open_store(store)
    for f in res["frames"]:      # kinds come from the store's frame metadata
        assert f["has_defocus"] == bool(st.meta_column("has_defocus")[f["index"]])
        assert f["has_motion"] == bool(st.meta_column("has_motion")[f["index"]])
    for kind, agg in res["by_kind"].items():
        sel = [f for f in res["frames"] if kind in frame_kinds(f)]
        assert agg["frames"] == len(sel) > 0
        assert agg["relmse"] == pytest.approx(np.mean([f["relmse"] for f in sel]))

    rep = tmp_path / "report"
    assert main(["report", "--runs", str(runs / "layer"), str(runs / "layer-optimized"), str(runs / "missing*"),
                 "--store", store, "--out", str(rep)]) == 0
    md = (rep / "report.md").read_text()
    for label in ("| input |", "| layer |", "| layer-optimized |", "| oidn |", "relMSE", "FMAs", "figure 10",
                  "relMSE by kind of frame"):
        assert label in md
    assert Image.open(rep / "speed_vs_error.png").size[0] > 100
    # inference timed at the bench's size, not on the store's small frames; the noisy input has no time
    assert "ms/MP @128²" in md and "one 128x128 frame" in md
    speed = json.loads((rep / "comparisons.json").read_text())["speed"]
    assert speed["input"] is None and speed["layer"]["size"] == 128 and speed["oidn"]["ms_per_mp"] > 0
    assert next(ln for ln in md.splitlines() if ln.startswith("| input |")).split("|")[9].strip() == "–"
    crops = Image.open(rep / "crops.png")
    assert crops.size[0] > 4 * crops.size[1] > 400          # 5 panels side by side: input, 2 models, oidn, reference
    assert res["mean"]["tpsnr"] is None and res["mean"]["spp"] == 2   # stills only: no temporal PSNR
    # the reference's own limits: evaluate's per-frame figures are validate's, and the report states them
    from stores.validate import validate_store
    rep_v = {f.index: f for f in validate_store(store).frames}
    for f in res["frames"]:
        assert f["ref_psnr_ceiling"] == pytest.approx(rep_v[f["index"]].psnr_ceiling, rel=1e-4)
        assert f["ref_relmse_floor"] == pytest.approx(rep_v[f["index"]].relmse_floor, rel=1e-4)
    assert res["reference"]["psnr_ceiling_lowest"] == pytest.approx(min(f["ref_psnr_ceiling"] for f in res["frames"]))
    assert "from their stored standard error" in md
    # provenance: the code, versions, the store's dataset config and each run's config and checkpoint hash
    prov = json.loads((rep / "provenance.json").read_text())
    assert prov["versions"]["torch"] and prov["versions"]["zarr"] and prov["machine"]["cpus"] >= 1
    assert prov["stores"]["evaluation"]["config"] == open_store(store).config
    import hashlib
    ck = runs / "layer" / "checkpoint.pt"
    assert prov["runs"][str(runs / "layer")]["sha256"] == hashlib.sha256(ck.read_bytes()).hexdigest()
    assert prov["runs"][str(runs / "layer")]["train_config"]["steps"] == 2 and "provenance.json" in md
    assert main(["report", "--runs", str(tmp_path / "nothing"), "--store", store, "--out", str(rep)]) == 2


def test_frame_kinds_put_the_scene_family_first(store):
    """A frame's family is the kind of its scene when the store's config made scenes of that kind; the
    store knows its families (training never asks the scene generator)."""
    from stores.reader import open_store
    from training.evaluate import frame_kinds, frame_tags, scene_families
    assert frame_kinds({"scene_kind": "indoor", "has_motion": True}) == ["indoor", "motion"]
    assert frame_kinds({"scene_kind": "outdoor"}) == ["outdoor", "plain"]
    assert frame_kinds({"scene_kind": "", "has_fireflies": True}) == ["fireflies"]
    st = open_store(store)                                       # a synthetic store: no scene families
    assert scene_families(st) == () and frame_tags(st, 0)["scene_kind"] == ""
    made = type("S", (), {"config": {"scenes": [{"kind": "indoor", "count": 2}, {"kind": "outdoor"},
                                                 {"kind": "indoor", "frames": 8}]}})()
    assert scene_families(made) == ("indoor", "outdoor")


def test_firefly_share_counts_outlier_pixels():
    """A pixel holds a firefly when one sample is 16x brighter than its reference (+0.05)."""
    import torch

    from training.evaluate import firefly_share
    ref = torch.full((3, 10, 10), 0.5)
    rad = torch.full((4, 3, 10, 10), 0.5)
    assert firefly_share(rad, ref) == 0.0
    rad[1, :, 2, 3] = 100.0                  # one sample, 200x its pixel's reference
    rad[0, :, 5, 5] = 8.0                    # 16x, below 16 * (0.5 + 0.05)
    rad[2, 0, 7, 7] = float("nan")           # renderer NaN: not a firefly
    assert firefly_share(rad, ref) == pytest.approx(0.01)


def test_oidn_baseline_denoises(store):
    """OIDN on the noisy mean beats the noisy input itself on the synthetic frames (heavy-tailed noise
    with x1e5 fireflies at 2 spp): far lower relMSE and higher SSIM."""
    from training.evaluate import evaluate
    noisy = evaluate("input", store, split="test", with_flip=False)
    oidn = evaluate("oidn", store, split="test", with_flip=False)
    assert oidn["mean"]["relmse"] < noisy["mean"]["relmse"] / 10
    assert oidn["mean"]["ssim"] > noisy["mean"]["ssim"]


def test_figure10_ordering():
    """Figure 10's shape: PIXELGATHER flat in spp; SAMPLESPLAT grows fastest; LAYER in between;
    OPTIMIZED cheapest."""
    from training.fma import figure10
    rows = {(r["model"], r["spp"]): r["fmas_per_pixel"] for r in figure10(spps=(2, 8, 32))}
    pg = [rows[("pixelgather", s)] for s in (2, 8, 32)]
    assert max(pg) / min(pg) < 1.01
    for s in (8, 32):
        assert rows[("layer-optimized", s)] < rows[("pixelgather", s)] < rows[("layer", s)] < rows[("samplesplat", s)]
    assert rows[("samplesplat", 32)] - rows[("samplesplat", 2)] > 5 * (rows[("layer", 32)] - rows[("layer", 2)])


def test_bench_runs_small():
    from training.bench import run
    res = run(size=32, spp=2, repeats=1, models=("pixelgather", "layer-optimized"), print_table=False)
    assert set(res) == {"pixelgather", "layer-optimized", "oidn"}
    assert all(v["ms_per_mp"] > 0 and v["ms_per_720p"] > 0 for v in res.values())


def test_timings_on_a_busy_machine_say_so():
    """A process spinning on a core shows in ``others_busy`` (the cores other processes kept busy while this
    one slept), and the report and the bench warn from half a core on."""
    import subprocess
    import sys

    from training.bench import busy_note, others_busy
    from training.report import _busy_lines
    spin = subprocess.Popen([sys.executable, "-c", "import time\nt = time.time()\nwhile time.time() - t < 5: pass"])
    try:
        time.sleep(0.3)
        assert others_busy(0.5) >= 0.5
    finally:
        spin.kill()
        spin.wait()
    assert busy_note(None) is None and busy_note(0.2) is None
    assert "1.5 of its" in busy_note(1.5) and "idle machine" in busy_note(1.5)
    quiet = [{"speed": {"ms_per_mp": 1.0, "others_busy_cores": 0.1}}, {"speed": None}]
    assert _busy_lines(quiet) == []
    busy = quiet + [{"speed": {"ms_per_mp": 2.0, "others_busy_cores": 1.7}}]
    assert _busy_lines(busy)[0].startswith("**The machine was busy while timing") and "1.7" in _busy_lines(busy)[0]


def test_bench_times_the_training_step_that_train_runs(monkeypatch):
    """``bench --train`` (and the GPU check, which calls it) times ``device_train_step`` with fused Adam,
    never the step that reads its loss every time."""
    from training import accel, bench, loop
    seen = {"steps": 0, "adam": 0}
    step, adam = loop.device_train_step, accel.adam

    def counted_step(*a, **k):
        seen["steps"] += 1
        return step(*a, **k)

    def counted_adam(*a, **k):
        seen["adam"] += 1
        return adam(*a, **k)
    monkeypatch.setattr(loop, "device_train_step", counted_step)
    monkeypatch.setattr(accel, "adam", counted_adam)
    monkeypatch.setattr(loop, "train_step", lambda *a, **k: pytest.fail("train_step reads the loss every step"))
    res = bench.train_run(models=["nbg"], seconds=0.05, crop=16, batch=2, precisions=("fp32", "bf16"),
                          print_table=False)
    row = res["nbg"]
    assert row["fp32"]["steps_per_s"] > 0 and row["bf16"]["steps_per_s"] > 0 and row["bf16_speedup"] > 0
    assert row["fp32"]["batch"] == 2 and row["fp32"]["crop"] == 16 and seen["adam"] == 2
    assert seen["steps"] == 3 + row["fp32"]["steps"] + 3 + row["bf16"]["steps"]
    import torch

    from training.models import build
    r = bench.time_model(build("nbg"), 1, (24, 40), 1, torch.device("cpu"), "fp32")
    assert r["size"] == [24, 40] and abs(r["ms_per_frame"] - r["ms_per_mp"] * 24 * 40 / 1e6) < 1e-6


def test_speed_vs_error_marks_what_it_cannot_place(tmp_path, monkeypatch):
    """A log relMSE axis over 4 decades from the best method: one far above is drawn on the top edge and
    named with its value, one that a log axis cannot hold is named, the input (no time) is a line."""
    from training import report
    drawn = {}

    def keep(fig_self, path, *a, **k):
        ax = fig_self.axes[0]
        drawn.update(ylim=ax.get_ylim(), labels=ax.get_legend().get_texts() and
                     [t.get_text() for t in ax.get_legend().get_texts()], yscale=ax.get_yscale())
    from matplotlib.figure import Figure
    monkeypatch.setattr(Figure, "savefig", keep)
    results = [{"label": "input", "mean": {"relmse": 0.57}},
               {"label": "nbg", "mean": {"relmse": 57.0}, "speed": {"ms_per_mp": 700.0}},
               {"label": "oidn", "mean": {"relmse": 0.046}, "speed": {"ms_per_mp": 1300.0}},
               {"label": "diverged", "mean": {"relmse": 5e4}, "speed": {"ms_per_mp": 900.0}},
               {"label": "broken", "mean": {"relmse": float("nan")}, "speed": {"ms_per_mp": 100.0}}]
    report.plot_speed_vs_error(results, tmp_path / "p.png")
    assert drawn["yscale"] == "log" and drawn["ylim"][0] < 0.046 and 57.0 < drawn["ylim"][1] < 5e4
    assert drawn["labels"] == ["input (no time)", "nbg", "oidn", "diverged (relMSE 5e+04: above the plot)",
                               "broken (relMSE nan: not plotted)"]


def test_a_split_without_a_complete_frame_says_what_the_store_holds(tmp_path, capsys):
    """evaluate on a store whose complete frames are all in other splits names the split, the store's
    frames and its complete ones, none of them in the split; never "no complete frame (4 frames, 2 complete)"."""
    from stores.reader import open_store
    from stores.writer import StoreWriter
    store = make_store(tmp_path / "s.zarr", h=16, w=16, spp=2, per_split=(2, 0, 2))
    test = open_store(store).frames_in_split("test")
    for i in test:
        StoreWriter(store).mark_failed(i, "cut short")
    argv = ["evaluate", "--checkpoint", "input", "--store", store, "--out", str(tmp_path / "e.json"), "--no-flip",
            "--skip-bad-frames"]
    assert len(test) == 2 and main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"split 'test' of {store} has no complete frame (the store has 4 frames, 2 " \
        "complete, none of them in 'test')" in err, err
    for i in range(4):
        StoreWriter(store).mark_failed(i, "cut short")
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "has no complete frame (none of the store's 4 frames is complete)" in err, err
