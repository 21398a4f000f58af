"""The scaling study (studies.scaling*): nested subsets by clip on a tiny store, the fit on synthetic points
with known a, b, c, the target inversion and its refusal below the floor, the report writer on synthetic
results (no rendering, no training), and one tiny run that a second call finds finished."""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from training.errors import ConfigError, DataError, TargetBelowFloorError
from studies.scaling import (Job, ScalingConfig, clip_table, family_subsets, load_scaling_config, nested_subsets,
                              plan)
from studies.scaling_fit import bootstrap_fit, frames_for_target, power_law, support

ROOT = Path(__file__).resolve().parents[1]


def make_family_store(path, stills=6, clips=2, clip_frames=3, h=16, w=16, split=None):
    """Stills and clips of two scene families (indoor, outdoor alternating), every scene in one split."""
    from stores.schema import StoreLayout
    from stores.writer import open_or_create
    from test_stores_synthetic import synthetic_frame
    scenes = [(s, 1) for s in range(stills)] + [(100 + c, clip_frames) for c in range(clips)]
    layout = StoreLayout(num_frames=sum(n for _, n in scenes), height=h, width=w, spp=2, tile=16)
    writer = open_or_create(str(path), layout, {"test": True, "split": split or {"train": 1}})
    i = 0
    for k, (seed, n) in enumerate(scenes):
        for f in range(n):
            fr = synthetic_frame(seed, h, w, 2, frame=f, num_frames=n, sun=False, scene_seed=seed,
                                 motion=n > 1)
            fr["meta"]["scene_json"] = json.dumps({"kind": ("indoor", "outdoor")[k % 2], "seed": seed})
            writer.write_frame(i, fr)
            i += 1
    return str(path)


@pytest.fixture(scope="module")
def stores(tmp_path_factory):
    d = tmp_path_factory.mktemp("scaling")
    return (make_family_store(d / "train.zarr"),
            make_family_store(d / "heldout.zarr", stills=4, clips=1, split={"test": 1}))


def test_subsets_are_nested_clips_whole_and_a_function_of_the_seed(stores):
    from training.data import model_dataset, open_store
    from training.models import get
    st = open_store(stores[0])
    table = clip_table(st, "train")
    frames = {c: len(v["frames"]) for c, v in table.items()}
    assert sorted(frames.values()) == [1] * 6 + [3, 3] and {v["family"] for v in table.values()} == {"indoor", "outdoor"}
    subs = nested_subsets(frames, [0.25, 0.5, 1.0], seed=3)
    assert subs == nested_subsets(frames, [1.0, 0.5, 0.25], seed=3)          # a function of the seed alone
    assert any(nested_subsets(frames, [0.25, 0.5, 1.0], seed=s) != subs for s in range(4, 8))
    for small, big in zip(subs, subs[1:]):
        assert set(small["clips"]) < set(big["clips"])                          # nested
    assert subs[-1]["frames"] == 12 and set(subs[-1]["clips"]) == set(frames)
    for sub in subs:
        assert sub["frames"] == sum(frames[c] for c in sub["clips"])             # clips whole
        assert abs(sub["frames"] - sub["share"] * 12) <= 3                       # nearest prefix
    # training reads exactly the frames of the subset's clips
    ds = model_dataset(get("nbg").inputs, st, "train", 1, None, augment=False, seed=0, clips=subs[1]["clips"])
    used = sorted(i for w in ds.windows for i in w)
    assert used == sorted(i for c in subs[1]["clips"] for i in table[c]["frames"])
    # the variety axis: the same frames of one family, or of both
    fam = family_subsets(frames, {c: v["family"] for c, v in table.items()}, 4, seed=0)
    assert set(fam) == {"indoor", "outdoor", "both"}
    for name, sub in fam.items():
        kinds = {table[c]["family"] for c in sub["clips"]}
        assert kinds == ({"indoor", "outdoor"} if name == "both" else {name}) and abs(sub["frames"] - 4) <= 2


def _points(a, b, c, sign, sizes=(8, 16, 32, 64, 128), seeds=3, frames=40, noise=0.01, seed=0):
    """Runs on the same held-out frames: the curve plus a frame's own difficulty, a seed's offset and noise."""
    rng = np.random.default_rng(seed)
    difficulty = rng.normal(0, 5 * noise, frames)
    return [{"n": n, "seed": s, "values": power_law(n, a, b, c, sign) + difficulty + rng.normal(0, noise)
             + rng.normal(0, noise, frames)} for n in sizes for s in range(seeds)], np.arange(frames) // 2


@pytest.mark.parametrize("a,b,c,sign,metric", [(3.0, 0.8, 0.05, 1, "relmse"), (40.0, 0.6, 28.0, -1, "psnr")])
def test_fit_recovers_known_parameters_within_its_intervals(a, b, c, sign, metric):
    noise = 0.004 if sign > 0 else 0.05
    points, clips = _points(a, b, c, sign, noise=noise)
    fit = bootstrap_fit(points, clips, sign, resamples=200)
    assert fit["failed"] == 0
    for k, v in (("a", a), ("b", b), ("c", c)):
        lo, hi = fit["ci95"][k]
        assert lo <= v <= hi, (k, v, fit["ci95"][k])
        assert lo <= fit[k] <= hi
    assert fit["ci95"]["b"][1] - fit["ci95"]["b"][0] < 0.5
    assert support(points, clips, sign)["supported"]
    # flat points (no gain with more frames) do not support a fit, and say why
    flat, _ = _points(0.0, 0.5, c, sign, noise=noise)
    why = support(flat, clips, sign)
    assert not why["supported"] and "not shown to differ" in why["reason"]


def test_target_inversion_and_its_refusal_below_the_floor():
    points, clips = _points(3.0, 0.8, 0.05, 1, noise=0.004)
    fit = bootstrap_fit(points, clips, 1, resamples=200)
    ans = frames_for_target(fit, 0.08, "relmse")
    expect = (fit["a"] / (0.08 - fit["c"])) ** (1 / fit["b"])
    assert ans["frames"] == pytest.approx(expect)
    assert ans["ci95"][0] <= ans["frames"] <= ans["ci95"][1]
    assert ans["ci95"][0] <= (3.0 / 0.03) ** (1 / 0.8) <= ans["ci95"][1]          # the true N, within the interval
    assert power_law(ans["frames"], fit["a"], fit["b"], fit["c"]) == pytest.approx(0.08)
    with pytest.raises(TargetBelowFloorError, match=r"below the fitted floor 0\.0\d+ \(95% interval"):
        frames_for_target(fit, 0.01, "relmse")
    points, clips = _points(40.0, 0.6, 28.0, -1, noise=0.05)
    fit = bootstrap_fit(points, clips, -1, resamples=200)
    assert frames_for_target(fit, 27.0, "psnr")["frames"] > 0
    with pytest.raises(TargetBelowFloorError, match="above the fitted ceiling 2[78]"):
        frames_for_target(fit, 40.0, "psnr")


def _config(**kw) -> ScalingConfig:
    base = dict(train_data={}, heldout_data={}, models=[{"model": "nbg", "steps": 2}],
                subsets=[0.125, 0.25, 0.5, 1.0], seeds=[0, 1], variety={"seeds": [0]},
                train={"batch": 2, "crop": 16, "val_every": 0, "workers": 0}, resamples=100)
    return ScalingConfig(**{**base, **kw})


def _synthetic_records(jobs, held=20):
    """Evaluations as ``scaling_run`` writes them, made up: relMSE and PSNR on a known curve, the variety runs
    better on their own family."""
    rng = np.random.default_rng(1)
    fams = ["indoor", "outdoor"] * (held // 2)
    out = {}
    for j in jobs:
        n = j.frames or 10_000
        frames = []
        for i in range(held):
            own = j.family in (None, "both", fams[i])
            rel = power_law(n, 2.0, 0.7, 0.04) * (1.0 if own else 1.5) + rng.normal(0, 0.002)
            frames.append({"index": 100 + i, "clip": i // 2, "scene_kind": fams[i], "relmse": rel,
                           "psnr": power_law(n, 30.0, 0.5, 30.0, -1) + rng.normal(0, 0.05)})
        mean = {k: float(np.mean([f[k] for f in frames])) for k in ("relmse", "psnr")}
        out[j.name] = {"job": j.to_dict(), "seconds": 1.0,
                       "evaluation": {"frames": frames, "mean": mean, "ci95": dict.fromkeys(mean)}}
    return out


def test_report_writer_on_synthetic_results(tmp_path):
    from studies.scaling_report import analyse, write_report
    scfg = _config()
    table = {c: {"frames": [c], "family": ("indoor", "outdoor")[c % 2]} for c in range(64)}
    jobs, record = plan(scfg, table)
    assert {j.kind for j in jobs} == {"subset", "variety", "baseline"}
    assert sorted({j.frames for j in jobs if j.kind == "subset"}) == [8, 16, 32, 64]
    costs = {"dataset": "synthetic", "core_hours_per_frame": 0.01, "bytes_per_frame": 5e5, "store_fixed_bytes": 1e4,
             "workers": 2, "threads": 1}
    res = analyse(scfg, jobs, _synthetic_records(jobs), {"relmse": 0.06, "psnr": 31.0}, costs)
    res.update(config=scfg.to_dict(), stores={"train": "t.zarr", "heldout": "h.zarr"}, plan=record, seconds=3.0)
    write_report(tmp_path, res, scfg)
    md = (tmp_path / "scaling.md").read_text()
    assert (tmp_path / "scaling.png").read_bytes()[:4] == b"\x89PNG"
    for text in ("## Verdicts", "nbg: more data helps: relMSE", "| 8 | 0, 1 |", "| 64 | 0, 1 |",
                 "| nbg | relMSE |", "| yes |", "## Scene variety", "| indoor | 32 |", "| both | 32 |",
                 "vs both", "## Frames for a target", "core-hours", "PSNR 31: refused: psnr target 31 is above the "
                 "fitted ceiling", "input @1spp", "oidn @1spp"):
        assert text in md, text
    data = json.loads((tmp_path / "scaling.json").read_text())
    fit = data["models"]["nbg"]["curves"]["relmse"]["fit"]
    assert fit["ci95"]["b"][0] <= 0.7 <= fit["ci95"]["b"][1] and fit["ci95"]["c"][0] <= 0.04 <= fit["ci95"]["c"][1]
    assert "samples" not in fit and data["plan"]["subsets"]["0"][0]["clips"]
    answer = next(t for t in data["targets"] if t["metric"] == "relmse")
    assert answer["frames"] > 0 and answer["cost"]["core_hours"] == pytest.approx(0.01 * answer["frames"])
    indoor = next(r for r in data["variety"][0]["rows"] if r["trained_on"] == "indoor")
    assert indoor["cells"]["outdoor"]["vs_both"]["shown"] and indoor["cells"]["outdoor"]["vs_both"]["mean"] > 0


def test_config_checks_and_the_shipped_configs():
    for name in ("scaling-smoke.yaml", "scaling-cpu.yaml"):
        scfg = load_scaling_config(ROOT / "configs" / name)
        train, held = scfg.dataset_configs()
        assert set(held.scene_splits()) == {"test"} and set(train.scene_splits()) == {"train"}
        assert not {s.seed for s in [train]} & {s.seed for s in [held]}      # other seeds, other scenes
    # the steps and variety studies reuse the stores of scaling-cpu.yaml: the same datasets where they are written
    base = load_scaling_config(ROOT / "configs" / "scaling-cpu.yaml")
    for name in ("scaling-cpu-steps.yaml", "scaling-cpu-variety.yaml"):
        other = load_scaling_config(ROOT / "configs" / name)
        for a, b in zip(base.dataset_configs(), other.dataset_configs()):
            assert dataclasses.replace(a, out=None) == dataclasses.replace(b, out=None), name
            assert b.store_path(b.out) == a.store_path(f"{Path(base.out) / 'stores'}/"), name
    with pytest.raises(ConfigError, match="scaling.subsets"):
        _config(subsets=[0.5, 1.5])
    with pytest.raises(ConfigError, match="scaling.variety.models"):
        _config(variety={"models": ["wskpn"]})
    with pytest.raises(ConfigError, match="train_clips"):
        _config(models=[{"model": "nbg", "train_clips": [1]}])


def test_a_run_is_trained_once_and_then_found_finished(stores, tmp_path):
    import torch

    from training.data import open_store
    from studies.scaling_run import RECORD, finished, heldout_identity, run_job, run_jobs
    scfg = _config(subsets=[0.5, 1.0], seeds=[0], variety=None)
    jobs, _ = plan(scfg, clip_table(open_store(stores[0]), "train"))
    job = next(j for j in jobs if j.kind == "subset")
    held = json.loads(json.dumps(heldout_identity(open_store(stores[1]))))
    threads = torch.get_num_threads()
    try:
        res = run_job(job.to_dict(), stores[0], stores[1], str(tmp_path / "runs" / job.name), 1, False, held)
    finally:
        torch.set_num_threads(threads)
    rec = finished(job, tmp_path / "runs" / job.name, held)
    assert rec is not None and rec["evaluation"]["train_steps"] == 2 and np.isfinite(res["mean"]["relmse"])
    assert rec["job"]["clips"] == list(job.clips) and len(rec["evaluation"]["frames"]) == 7
    assert (tmp_path / "runs" / job.name / "checkpoint.pt").is_file()
    lines = []
    got = run_jobs([job], stores[0], stores[1], tmp_path, 1, 1, False, log=lines.append)    # no pool: finished
    assert got[job.name]["seconds"] == rec["seconds"] and "1 finished, 0 to run" in lines[0]
    other = Job(**{**job.to_dict(), "clips": tuple(job.clips), "train_config": {**job.train_config, "steps": 3}})
    assert finished(other, tmp_path / "runs" / job.name, held) is None                       # more steps: not done
    assert json.loads((tmp_path / "runs" / job.name / RECORD).read_text())["heldout"] == held


@pytest.mark.slow
def test_the_smoke_study_runs_end_to_end_and_resumes(tmp_path):
    """`python -m studies scaling --config configs/scaling-smoke.yaml --out DIR` as a user runs it (about a
    minute): it renders its stores, trains and evaluates every run and writes the three files, with every
    run's mean in the JSON; run again, it trains nothing and reads every run as finished."""
    import subprocess
    import sys

    from test_pipeline_safety import _env
    root = Path(__file__).resolve().parent.parent
    argv = [sys.executable, "-m", "studies", "scaling", "--config", str(root / "configs" / "scaling-smoke.yaml"),
            "--out", str(tmp_path), "--no-progress"]
    first = subprocess.run(argv, env=_env(), cwd=root, capture_output=True, text=True, timeout=900)
    assert first.returncode == 0, first.stdout[-3000:] + first.stderr[-3000:]
    for name in ("scaling.md", "scaling.png", "scaling.json"):
        assert (tmp_path / name).is_file() and (tmp_path / name).stat().st_size > 0, name
    res = json.loads((tmp_path / "scaling.json").read_text())
    assert res["runs"] and all(np.isfinite(r["mean"]["relmse"]) for r in res["runs"])
    assert "| " in (tmp_path / "scaling.md").read_text()
    again = subprocess.run(argv, env=_env(), cwd=root, capture_output=True, text=True, timeout=900)
    assert again.returncode == 0, again.stderr[-3000:]
    n = len(res["runs"])
    assert f"{n} finished, 0 to run" in again.stdout + again.stderr, again.stdout[-2000:]


HELD_STORES = """
import studies.scaling_run
stores = {stores!r}
studies.scaling_run.ensure_store = lambda dcfg, *a, **k: stores[dcfg.name]
"""


@pytest.mark.parametrize("when", ["starting", "training"])
def test_ctrl_c_pressed_five_times_is_one_line(stores, tmp_path, when):
    """`python -m studies scaling` (its stores the synthetic ones, by a hook) pressed Ctrl-C five times 0.1 s
    apart as its pool's workers start, and once a run trains: exit 130 and the study's one line, last on
    stderr. Before, a press while the study exited ended it by SIGINT (exit -2; the pool's semaphores could
    leak, and resource_tracker warned after the line), and one that reached a worker before it ignored
    Ctrl-C printed the worker's KeyboardInterrupt traceback."""
    import yaml
    from procs import Command, kill_group, last_line, python_m
    smoke = yaml.safe_load((ROOT / "configs" / "scaling-smoke.yaml").read_text())
    study = {**smoke, "subsets": [0.5, 1.0], "seeds": [0], "variety": None,
             "models": [{"model": "nbg", "steps": 100000}], "train": {**smoke["train"], "checkpoint_every": 100000}}
    (tmp_path / "study.yaml").write_text(yaml.safe_dump(study))
    names = (smoke["train_data"]["name"], smoke["heldout_data"]["name"])
    out = tmp_path / "study"
    proc = Command(python_m("studies", HELD_STORES.format(stores=dict(zip(names, stores)))) +
                   ["scaling", "--config", str(tmp_path / "study.yaml"), "--out", str(out), "--no-progress"])
    try:
        proc.wait_for("scaling: ")
    except BaseException:
        kill_group(proc)
        raise
    proc.ctrl_c_when(lambda: when != "training" or any("train nbg" in p.read_text()
                                                        for p in out.glob("runs/**/run.log")))
    code, _, err = proc.finish()
    assert code == 130, err[-3000:]
    last_line(err, "interrupted: rendered frames, finished runs and the runs' last checkpoints stay; the same "
                   "command resumes")


def test_training_has_no_scaling_command_and_names_the_studies_one(capsys, monkeypatch):
    """The study lives above training: `python -m training scaling` starts nothing (no `python -m studies`
    child) and says in one line where the command is."""
    import subprocess

    from training.__main__ import main
    from training.commands import parser
    started = []
    monkeypatch.setattr(subprocess, "Popen", lambda *a, **k: started.append(a))
    assert main(["scaling", "--config", str(ROOT / "configs" / "scaling-smoke.yaml"), "--out", "x"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("error: ") and "`python -m studies scaling`" in err, err
    assert started == [] and "scaling" not in parser().format_help()


def test_hard_share_subsets_plan_and_checks():
    from studies.scaling import hard_subsets
    frames = {c: 1 for c in range(40)}
    cases = {c: ("sun" if c >= 30 else "") for c in range(40)}          # 30 ordinary, 10 hard stills
    subs = hard_subsets(frames, cases, 20, [0.0, 0.1, 0.25], seed=3)
    assert [subs[s]["hard_frames"] for s in (0.0, 0.1, 0.25)] == [0, 2, 5]
    assert all(v["frames"] == 20 and len(v["clips"]) == 20 for v in subs.values())
    hard = {s: {c for c in v["clips"] if cases[c]} for s, v in subs.items()}
    assert hard[0.1] <= hard[0.25]                                       # the hard clips nest
    assert hard_subsets(frames, cases, 20, [0.25], seed=3) == {0.25: subs[0.25]}   # a function of the seed
    with pytest.raises(DataError, match="need 20 hard-case training frames; the store has 10"):
        hard_subsets(frames, cases, 20, [0.0, 1.0], seed=0)
    h = dict(models=["nbg"], seeds=[0, 1], frames=20, shares=[0, 0.25])
    suite = {"held_out": True, "split": {"test": 1}, "scenes": [{"kind": "indoor", "count": 1, "case": "black"}]}
    scfg = _config(subsets=[], variety=None, hard_share=h, hard_data=suite)
    table = {c: {"frames": [c], "family": "indoor", "case": cases[c]} for c in range(40)}
    jobs, record = plan(scfg, table)
    hard_jobs = [j for j in jobs if j.kind == "hard"]
    assert sorted((j.seed, j.share) for j in hard_jobs) == [(0, 0.0), (0, 0.25), (1, 0.0), (1, 0.25)]
    assert all(j.frames == 20 for j in hard_jobs) and record["hard_share"]["0"]["0.25"]["hard_frames"] == 5
    for bad, needle in (({"shares": [0.1, 0.25]}, "0 among them"), ({"models": ["wskpn"]}, "hard_share.models"),
                        ({"shares": [0, 1.5]}, "hard_share.shares")):
        with pytest.raises(ConfigError, match=needle):
            _config(subsets=[], hard_share={**h, **bad}, hard_data=suite)
    with pytest.raises(ConfigError, match="scaling.hard_data must be a held-out hard-case suite"):
        _config(subsets=[], hard_share=h)
    with pytest.raises(ConfigError, match="scaling.hard_data must be a held-out dataset"):
        _config(subsets=[], hard_share=h, hard_data={"scenes": [{"kind": "indoor", "count": 1}]}).hard_config()


def test_hard_share_analysis_on_synthetic_results(tmp_path):
    """Made-up evaluations: the runs trained with hard frames beat their input on the suite's case 'sun' and
    cost nothing on ordinary frames; the analysis says so, with intervals, and the report shows it."""
    from studies.scaling_report import analyse, write_report
    suite = {"held_out": True, "split": {"test": 1}, "scenes": [{"kind": "outdoor", "count": 1, "case": "sun"}]}
    scfg = _config(subsets=[], variety=None, hard_data=suite,
                   hard_share=dict(models=["nbg"], seeds=[0, 1], frames=20, shares=[0, 0.25]))
    cases = {c: ("sun" if c >= 30 else "") for c in range(40)}
    jobs, record = plan(scfg, {c: {"frames": [c], "family": "indoor", "case": cases[c]} for c in range(40)})
    rng = np.random.default_rng(0)
    records = _synthetic_records(jobs)
    for j in jobs:                    # the suite: 8 sun frames in 4 clips; input 1.0, runs 0.5 (0%) and 0.1 (25%)
        rel = {"baseline": 1.0 if j.method == "input" else 0.3}.get(j.kind, 0.5 if j.share == 0 else 0.1)
        frames = [{"index": i, "clip": i // 2, "relmse": rel + rng.normal(0, 0.01), "psnr": 20 - 5 * rel
                   + rng.normal(0, 0.05)} for i in range(8)]
        records[j.name]["hard_evaluation"] = {"frames": frames}
    res = analyse(scfg, jobs, records, {}, suite_cases={i: "sun" for i in range(8)})
    (nbg,) = res["hard_share"]
    sun = nbg["cases"]["sun"]
    assert sun["0.25"]["vs_input"]["verdict"] == "beats" and sun["0.25"]["vs_none"]["relmse"]["mean"] < -0.3
    assert sun["0.25"]["relmse_ci95"][0] < 0.1 < sun["0.25"]["relmse_ci95"][1]
    assert sun["input"]["relmse"] == pytest.approx(1.0, abs=0.02) and sun["oidn"]["vs_input"]["verdict"] == "beats"
    assert not nbg["ordinary"]["0.25"]["psnr"]["vs_none"]["shown"]        # the same ordinary frames' values
    assert "nbg: at 0% hard frames it beats its noisy input on 1 of 1 cases" in nbg["verdict"]
    res.update(config=scfg.to_dict(), stores={"train": "t.zarr", "heldout": "h.zarr", "hard_cases": "s.zarr"},
               plan=record, seconds=1.0)
    write_report(tmp_path, res, scfg)
    md = (tmp_path / "scaling.md").read_text()
    for text in ("## Hard cases in the training data", "| nbg | 25% |", "### nbg on the held-out hard-case suite",
                 "| sun |", ": better", "input @1spp"):
        assert text in md, text
    assert not (tmp_path / "scaling.png").exists()                      # no size axis, no curves


def test_bad_study_settings_are_one_line_and_one_study_holds_a_folder(tmp_path, capsys):
    from stores.errors import StoreLockedError
    from stores.lock import StoreLock
    from studies.__main__ import main
    from studies.scaling_run import run_study
    with pytest.raises(ConfigError, match=r"scaling.models\[0\].steps must be an integer >= 1"):
        _config(models=[{"model": "nbg", "steps": 0}])
    with pytest.raises(ConfigError, match=r"scaling.targets.psnr must be null or a PSNR > 0 dB, got -5"):
        _config(targets={"psnr": -5})
    assert main(["scaling", "--config", str(ROOT / "configs" / "scaling-smoke.yaml"), "--target-psnr", "-5",
                 "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err                       # the flag as typed, never "--target.psnr"
    assert err == "error: --target-psnr must be a PSNR > 0 dB, got -5.0\n", err
    with StoreLock(str(tmp_path / "study")):           # another study runs in this folder
        with pytest.raises(StoreLockedError, match="dataset.lock"):
            run_study(_config(), tmp_path / "study", progress=False)


REALISM = dict(models=["nbg"], seeds=[0, 1], suite={"held_out": True, "scenes": [{"kind": "indoor", "count": 1}]},
               filters=["box", "gaussian"], levels={"natural-textures": {"scene_gen": {"p_natural_textures": 1.0}},
                                                    "panels-in-view": {"scene_gen": {"p_panels_in_view": 1.0}}})


def test_realism_plan_levels_and_checks():
    """The realism axis: one run a model, seed and level (model by model, `none` first) on every training clip
    of the level's store; the levels' stores must hold the same clips; each level's dataset is the training
    config with its settings over the training config's, and a bad one is one line naming the level."""
    train = {"name": "tr", "scenes": [{"kind": "indoor", "count": 4}], "split": {"train": 1},
             "scene_gen": {"p_lamps": 0.1}}
    scfg = _config(subsets=[], variety=None, realism=REALISM, train_data=train,
                   models=[{"model": "nbg", "steps": 2}, {"model": "wskpn", "steps": 2}])
    assert scfg.realism_plan()["models"] == ["nbg"]
    levels = scfg.level_configs()
    assert list(levels) == ["none", "natural-textures", "panels-in-view"]
    assert levels["natural-textures"].name == "tr-natural-textures"
    assert levels["natural-textures"].scene_gen == {"p_lamps": 0.1, "p_natural_textures": 1.0}
    assert levels["none"].scenes == levels["panels-in-view"].scenes           # the same scenes, one property more
    assert {f: c.render.get("filter", "box") for f, c in scfg.suite_configs().items()} == \
        {"box": "box", "gaussian": "gaussian"}
    table = {c: {"frames": [c], "family": "indoor", "case": ""} for c in range(4)}
    jobs, record = plan(scfg, table, {lv: table for lv in levels})
    runs = [(j.label, j.seed, j.level) for j in jobs if j.kind == "realism"]
    assert runs == [("nbg", s, lv) for s in (0, 1) for lv in levels]
    assert all(j.frames == 4 and j.clips == (0, 1, 2, 3) for j in jobs if j.kind == "realism")
    assert record["realism"]["frames"] == 4 and "level" not in next(j for j in jobs if j.kind == "baseline").to_dict()
    with pytest.raises(DataError, match="level 'panels-in-view'.s training store holds 3 frames"):
        plan(scfg, table, {**{lv: table for lv in levels}, "panels-in-view": {c: table[c] for c in range(3)}})
    for bad, needle in (({"levels": {"none": {"scene_gen": {"p_lamps": 1}}}}, "scaling.realism.levels"),
                        ({"levels": {"x": {}}}, r"scaling.realism.levels.x"),
                        ({"filters": ["box", "triangle"]}, "scaling.realism.filters"),
                        ({"models": ["unet"]}, "scaling.realism.models")):
        with pytest.raises(ConfigError, match=needle):
            _config(subsets=[], realism={**REALISM, **bad}, train_data=train)
    with pytest.raises(ConfigError, match=r"scaling.realism.levels.x: dataset.scene_gen.p_lamps must be a probability"):
        _config(subsets=[], realism={**REALISM, "levels": {"x": {"scene_gen": {"p_lamps": 2}}}},
                train_data=train).level_configs()
    with pytest.raises(ConfigError, match="scaling.realism.suite must be a held-out dataset"):
        _config(subsets=[], realism={**REALISM, "suite": train}, train_data=train).suite_configs()


def test_realism_analysis_on_synthetic_results(tmp_path):
    """Made-up evaluations: the runs trained with natural textures halve their error on the suite's
    'interior' (both filters) and change nothing on ordinary frames or on 'box'; the analysis says so, with
    intervals, against `none`, the input and OIDN, and the report shows it."""
    from studies.scaling_report import analyse, write_report
    scfg = _config(subsets=[], variety=None, realism={**REALISM, "levels": {"natural-textures": REALISM["levels"][
        "natural-textures"]}})
    table = {c: {"frames": [c], "family": "indoor", "case": ""} for c in range(10)}
    jobs, record = plan(scfg, table, {"none": table, "natural-textures": table})
    records = _synthetic_records(jobs)
    for j in jobs:
        evs = {}
        for f in ("box", "gaussian"):      # 8 frames in 4 clips: 'box' 0-3, 'interior' 4-7
            frames = []
            for i in range(8):
                rel = {"input": 1.0, "oidn": 0.2}.get(j.method) if j.kind == "baseline" else \
                    (0.4 if i < 4 or j.level == "none" else 0.2)
                noise = np.random.default_rng([i, len(f)]).normal(0, 0.02, 2)   # the same frame, the same noise
                frames.append({"index": i, "clip": i // 2, "relmse": rel * (1 + noise[0]),
                               "psnr": 30 - 10 * rel + noise[1]})
            evs[f] = {"frames": frames}
        records[j.name]["real_evaluation"] = evs
    scenes = ["box"] * 4 + ["interior"] * 4
    res = analyse(scfg, jobs, records, {}, real_scenes={"box": scenes, "gaussian": scenes})
    (nbg,) = res["realism"]
    for f in ("box", "gaussian"):
        t = nbg["suite"][f]
        assert t["interior"]["natural-textures"]["vs_none"]["verdict"] == "better"
        assert t["interior"]["natural-textures"]["vs_none"]["relmse"]["mean"] == pytest.approx(-0.2, abs=0.02)
        assert t["box"]["natural-textures"]["vs_none"]["verdict"] == "not shown"
        assert t["interior"]["none"]["vs_input"]["verdict"] == "beats"
        assert t["interior"]["natural-textures"]["vs_oidn"]["relmse_ratio"] == pytest.approx(1.0, abs=0.05)
        assert t["(all)"]["input"]["relmse"] == pytest.approx(1.0, abs=0.02)
    assert not nbg["ordinary"]["natural-textures"]["psnr"]["vs_none"]["shown"]
    (line,) = nbg["verdicts"]
    # half the suite's clips unchanged: over all of it the interval reaches 0; on the interior it does not
    assert line.startswith("nbg, natural-textures against none: box filter: not shown on the whole suite, relMSE "
                           "-0.0") and "(-25%); better on interior; gaussian filter" in line, line
    res.update(config=scfg.to_dict(), stores={"train": "t.zarr", "heldout": "h.zarr",
                                              "levels": {"none": "t.zarr", "natural-textures": "n.zarr"},
                                              "real_scenes": {"box": "r.zarr", "gaussian": "g.zarr"}},
               plan=record, seconds=1.0)
    write_report(tmp_path, res, scfg)
    md = (tmp_path / "scaling.md").read_text()
    for text in ("## Properties of real scenes in the training data", "| nbg | natural-textures |",
                 "### nbg on the real-scene suite, gaussian filter", "| interior |", "x OIDN", ": better",
                 "`natural-textures` (`n.zarr`)"):
        assert text in md, text


def test_the_shipped_realism_study_reuses_the_held_out_stills_and_writes_the_suite_where_missing(tmp_path, monkeypatch):
    """configs/scaling-cpu-realism.yaml: its held-out stills are configs/scaling-cpu.yaml's (one store for
    both), its levels the same scenes with one property each, its suite the held-out real-scene suite with
    both filters, named as `make real-scenes` names them; loading it writes the suite's files where none are
    (a fresh clone) and reads them where they are."""
    monkeypatch.setenv("DENOISE_DATA", str(tmp_path))
    lines = []
    import studies.scaling as sc
    monkeypatch.setattr(sc, "print", lines.append, raising=False)
    scfg = load_scaling_config(ROOT / "configs" / "scaling-cpu-realism.yaml")
    assert (tmp_path / "real-scenes" / "cornell-box.xml").is_file()
    assert lines and "writing the real-scene suite's scene files" in lines[0]
    base = load_scaling_config(ROOT / "configs" / "scaling-cpu.yaml")
    held, base_held = scfg.dataset_configs()[1], base.dataset_configs()[1]
    assert held.store_path(held.out) == base_held.store_path(f"{Path(base.out) / 'stores'}/")
    assert dataclasses.replace(held, out=None) == dataclasses.replace(base_held, out=None)
    levels = scfg.level_configs()
    assert set(levels) == {"none", "natural-textures", "panels-in-view"}
    assert {lv: c.scene_gen.get("p_natural_textures", 0) + c.scene_gen.get("p_panels_in_view", 0)
            for lv, c in levels.items()} == {"none": 0, "natural-textures": 1.0, "panels-in-view": 1.0}
    assert len({c.frames()[5].seed for c in levels.values()}) == 1                 # the same scenes
    suites = scfg.suite_configs()
    assert {f: c.name for f, c in suites.items()} == {"box": "real-scenes", "gaussian": "real-scenes-gaussian"}
    assert all(c.held_out for c in suites.values()) and scfg.realism_plan()["models"] == ["nbg", "wskpn", "layer", "nppd"]


def test_models_narrow_a_study_to_the_runs_of_those_models(capsys):
    """``--models nbg``: only nbg's runs and its baselines, every axis narrowed; the same jobs, by name and
    settings, as the whole study's for nbg (so its finished runs are read back); an unknown label is one
    line."""
    from studies.__main__ import main
    train = {"name": "tr", "scenes": [{"kind": "indoor", "count": 4}], "split": {"train": 1}}
    scfg = _config(subsets=[], variety=None, train_data=train, realism={**REALISM, "models": ["nbg", "wskpn"]},
                   models=[{"model": "nbg", "steps": 2}, {"model": "wskpn", "steps": 2}])
    table = {c: {"frames": [c], "family": "indoor", "case": ""} for c in range(4)}
    tables = {lv: table for lv in scfg.level_configs()}
    whole = {j.name: j for j in plan(scfg, table, tables)[0]}
    narrow = plan(scfg.only_models(["nbg"]), table, tables)[0]
    assert {j.label for j in narrow if j.kind == "realism"} == {"nbg"} and len(narrow) == 6 + 2
    assert all(whole[j.name] == j for j in narrow)                      # the whole study's jobs, unchanged
    with pytest.raises(ConfigError, match=r"--models must name models of the study \['nbg', 'wskpn'\], got \['unet'\]"):
        scfg.only_models(["unet"])
    assert main(["scaling", "--config", str(ROOT / "configs" / "scaling-smoke.yaml"), "--models", "layer",
                 "--out", "/nonexistent/x"]) == 2
    assert capsys.readouterr().err.startswith("error: --models must name models of the study ['nbg'], got ['layer']")
