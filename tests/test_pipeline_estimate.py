"""``python -m pipeline estimate``: a real calibration render of a tiny config, figures checked against
their definitions (samples exactly, core-hours and wall time from the calibrated frame times, store
bytes from a real store write)."""
from __future__ import annotations

import contextlib
import io
import json

import pytest

CONFIG = """
name: est
seed: 3
resolution: [12, 8]
scenes:
  - {kind: indoor, count: 3}
  - {kind: outdoor, count: 2, frames: 2}
render: {spp: 4, layer_levels: 3, ref_spp: 64, ref_passes: 8, ref_min_passes: 4, time_slices: 2}
scene_gen: {indoor_objects: 4, outdoor_objects: 5, material_palette: 2}
cluster: {kind: local, threads_per_worker: 1}
"""


@pytest.fixture(scope="module")
def estimated(tmp_path_factory):
    from pipeline.__main__ import main
    d = tmp_path_factory.mktemp("est")
    cfg = d / "est.yaml"
    cfg.write_text(CONFIG)
    out = d / "est.json"
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        rc = main(["estimate", "--config", str(cfg), "--workers", "3", "--json", str(out)])
    assert rc == 0
    return cfg, json.loads(out.read_text()), printed.getvalue()


def test_estimate_figures_follow_from_the_calibration(estimated, capsys):
    from pipeline.config import load_config
    path, res, _ = estimated
    p, cal = res["prediction"], res["calibration"]
    cfg = load_config(path)
    assert p["frames"] == 3 + 2 * 2
    assert p["samples"] == 7 * 12 * 8 * (4 + 7 + 64)                 # inputs + layers 1+2+4 + reference
    assert [f["group"] for f in cal["frames"]] == [0, 1]              # one scene of each group
    for f in cal["frames"]:
        assert f["reference_s"] > 0 and f["frame_s"] == pytest.approx(
            f["load_s"] + f["inputs_s"] + f["layers_s"] + f["reference_s"])
    g = {int(k): v for k, v in cal["group_frame_s"].items()}
    core_s = 3 * g[0] + 4 * g[1]                                      # CPU seconds of every frame
    worker_s = core_s / cfg.cluster.threads_per_worker
    assert p["core_hours"] == pytest.approx(core_s / 3600)
    assert p["worker_hours"] == pytest.approx(worker_s / 3600)
    assert p["wall_s"] == pytest.approx(max(worker_s / 3, max(f["frame_s"] for f in cal["frames"])))
    # bytes: measured on a real store of the config's layout; compressed below raw float32
    raw = 12 * 8 * (4 * 20 + 3 * 3 + 6 + 9) * 4
    assert 0.05 * raw < cal["bytes_per_frame"] < raw
    assert p["store_bytes"] == int(cal["store_fixed_bytes"] + 7 * cal["bytes_per_frame"])


def test_one_scene_a_group_of_several_says_how_to_calibrate_closer(estimated):
    printed = estimated[2]
    assert "core-hours:" in printed and "wall time:" in printed
    # the indoor group holds 3 scenes and one was calibrated: the note names the options
    assert "one calibration scene a group" in printed and "--scenes-per-group 3 --ref-passes 8" in printed


def test_more_workers_shorter_wall(estimated):
    from pipeline.config import load_config
    from pipeline.estimate import predict
    path, res, _ = estimated
    cfg, cal = load_config(path), res["calibration"]
    cal["group_frame_s"] = {int(k): v for k, v in cal["group_frame_s"].items()}
    one, many = predict(cfg, cal, 1), predict(cfg, cal, 1000)
    assert one["wall_s"] > many["wall_s"]
    assert many["wall_s"] == pytest.approx(max(f["frame_s"] for f in cal["frames"]))   # the slowest frame
    assert one["core_hours"] == many["core_hours"]


def test_estimate_bad_input_is_exit_2(tmp_path, capsys):
    from pipeline.__main__ import main
    cfg = tmp_path / "c.yaml"
    cfg.write_text(CONFIG)
    assert main(["estimate", "--config", str(cfg), "--workers", "0"]) == 2
    assert "--workers" in capsys.readouterr().err
    assert main(["estimate", "--config", str(cfg), "--ref-passes", "99"]) == 2
    assert "--ref-passes" in capsys.readouterr().err
    bad = tmp_path / "bad.yaml"
    bad.write_text(CONFIG.replace("spp: 4,", "spp: 0,"))
    assert main(["estimate", "--config", str(bad)]) == 2
    assert "spp" in capsys.readouterr().err
    huge = tmp_path / "huge.yaml"                        # inside the allowed range, beyond this machine's memory
    huge.write_text(CONFIG.replace("resolution: [12, 8]", "resolution: 16384"))
    assert main(["estimate", "--config", str(huge)]) == 2
    err = capsys.readouterr().err
    assert "resolution 16384x16384 cannot be rendered" in err and "Traceback" not in err and len(err.splitlines()) == 1


def test_calibration_renders_side_by_side(estimated):
    """The frames were calibrated in as many processes as the workers that share this machine (at most
    the 3 asked for), every frame timed at least once under that load."""
    from pipeline.estimate import local_slots
    _, res, _ = estimated
    cal = res["calibration"]
    assert cal["concurrent"] == min(3, local_slots(1))
    assert all(f["runs"] >= 1 for f in cal["frames"])
    assert sum(f["runs"] for f in cal["frames"]) % cal["concurrent"] == 0


def test_predicted_passes_match_the_stopping_rule():
    """The early stop predicted from the first 4 passes agrees on average with the renderer's stopping
    rule (``render_reference``: batch means, the same relative error) run to the end, on simulated
    passes with per-pixel noise of several levels; no target means every pass."""
    import dataclasses

    import numpy as np

    from pipeline.estimate import c4, predicted_passes
    from pipeline.render import RenderConfig, rel_stderr
    from pipeline.render.reference import _batch_stats
    assert c4(2) == pytest.approx(np.sqrt(2 / np.pi)) and c4(1000) == pytest.approx(1.0, abs=1e-3)
    rc = RenderConfig(res=(16, 16), ref_spp=4096, ref_passes=32, ref_min_passes=8, ref_target_rel_stderr=0.03,
                      reference="batch_means")
    assert predicted_passes(0.5, 4, dataclasses.replace(rc, ref_target_rel_stderr=None)) == 32
    assert predicted_passes(1e-6, 4, rc) == 8 and predicted_passes(10.0, 4, rc) == 32
    rng = np.random.default_rng(0)
    for sigma in (0.06, 0.1, 0.13):                           # stops around pass 4-20
        actual, predicted = [], []
        for _ in range(40):
            mean = rng.uniform(0.2, 1.0, (16, 16, 1)) * np.ones(3)
            passes = mean + sigma * mean * rng.standard_normal((32, 16, 16, 1)) * np.ones(3)
            stop = 32
            for p in range(rc.ref_min_passes, 32):
                cnt = np.full((16, 16, 1), float(p))
                m, s = _batch_stats(cnt, passes[:p].sum(0), (passes[:p] ** 2).sum(0))
                if rel_stderr(m, s) <= rc.ref_target_rel_stderr:
                    stop = p
                    break
            cnt = np.full((16, 16, 1), 4.0)
            m, s = _batch_stats(cnt, passes[:4].sum(0), (passes[:4] ** 2).sum(0))
            actual.append(stop)
            predicted.append(predicted_passes(rel_stderr(m, s), 4, rc))
        assert abs(np.mean(predicted) - np.mean(actual)) <= 0.05 * np.mean(actual) + 0.5, (sigma, predicted, actual)


def test_a_moments_reference_is_predicted_round_by_round():
    """``moments``: the rounds the renderer takes (a first of ref_min_passes, then what the error predicts)
    and the cost fit of launches and samples."""
    from pipeline.estimate import predicted_passes, predicted_rounds, reference_seconds
    from pipeline.render import RenderConfig
    rc = RenderConfig(res=(16, 16), ref_spp=4096, ref_passes=32, ref_min_passes=8, ref_target_rel_stderr=0.03)
    assert predicted_rounds(0.01, 4, rc) == [8]                      # converged at the first round
    assert predicted_rounds(0.064, 2, rc) == [8, 10]                 # 0.032 at 8: 8 * (0.032/0.03)^2 * 1.05 -> 10
    assert predicted_rounds(1.0, 2, rc) == [8, 32] and predicted_passes(1.0, 2, rc) == 32
    # t = 0.02 s a launch + 1e-4 s a sample a pixel, recovered from two points
    t = lambda launches, spp: 0.02 * launches + 1e-4 * spp         # noqa: E731
    assert reference_seconds(t(16, 256), 256, 16, t(19, 63), 63, 19, 4096, 16) == pytest.approx(t(16, 4096))
    assert reference_seconds(1.0, 256, 16, 0.1, 63, 19, 512, 16) == pytest.approx(2.0)   # no positive fit


def _kernel_files() -> list[str]:
    import os
    return sorted(os.listdir(os.environ["DRJIT_CACHE_DIR"]))


def test_calibration_processes_compile_into_an_empty_kernel_cache(tmp_path):
    """A calibration frame pays its kernels' compilation, as a new scene of a run does: its process's
    drjit kernel cache is the empty folder given to it, not the user's cache of earlier runs."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    from pipeline.estimate import _warm_worker
    with ProcessPoolExecutor(1, multiprocessing.get_context("spawn"), initializer=_warm_worker,
                             initargs=(1, str(tmp_path))) as pool:
        files = pool.submit(_kernel_files).result()
    assert [f for f in files if f.endswith(".bin")]        # the warm-up's kernels, compiled there
