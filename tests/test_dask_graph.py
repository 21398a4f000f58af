"""pipeline.graph + pipeline.dataset on cheap task functions (no rendering): keys, resources,
retries, failure records, resume. The real chain runs in tests/test_dask_dataset.py.

The stand-in render functions here live in the tests only: they return arrays of the contract's
shapes computed from (spec JSON, frame), so the real store writer, validator and Dask scheduler do
the rest.
"""
from __future__ import annotations

import hashlib
import json
import logging
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import zarr
from dask.utils import key_split

from pipeline import tasks
from pipeline.config import DatasetConfig, load_config
from pipeline.graph import Ref, build_graph, default_functions

ROOT = Path(__file__).resolve().parent.parent
SMOKE = ROOT / "configs" / "smoke.yaml"


def tiny_cfg(**tasks_kw) -> DatasetConfig:
    d = {"name": "tiny", "seed": 3, "resolution": [8, 4],
         "scenes": [{"kind": "indoor", "count": 1}, {"kind": "outdoor", "count": 1, "frames": 2}],
         "render": {"spp": 2, "layer_levels": 3, "ref_spp": 4, "ref_passes": 2, "ref_min_passes": 2},
         "tasks": {"retries": 1, "split_streams": True, **tasks_kw}, "cluster": {"dashboard_address": None}}
    return DatasetConfig.from_dict(d)


# ---- stand-in task functions (tests only) ------------------------------------------------------
def fake_spec(seed, kind, num_frames, res, scene_gen):
    from scene_gen.spec import CameraSpec, SceneSpec
    cams = tuple(CameraSpec(origin=(0.0, 1.0, 5.0 + f), target=(0.0, 0.0, 0.0)) for f in range(num_frames))
    return SceneSpec(kind=kind, seed=int(seed), objects=(), lights=(), cameras=cams).to_json()


def _rng(spec_json, frame, stream):
    h = hashlib.sha256(f"{spec_json}|{frame}|{stream}".encode()).digest()
    return np.random.default_rng(int.from_bytes(h[:8], "little"))


def fake_inputs(spec_json, frame, render):
    W, H = render["res"]
    S = render["spp"]
    r = _rng(spec_json, frame, "inputs")
    feats = np.zeros((H, W, S, 17), np.float32)
    feats[..., 3] = r.random((H, W, S))              # depth >= 0, the rest 0 (valid ranges)
    return {"radiance": r.random((H, W, S, 3), dtype=np.float32), "features": feats,
            "guides_albedo": np.zeros((H, W, 3), np.float32), "guides_normal": np.zeros((H, W, 3), np.float32),
            "guides_depth": feats[..., 3:4].mean(axis=2), "guides_motion": np.zeros((H, W, 2), np.float32),
            "camera_to_world": np.eye(4), "world_to_clip": np.eye(4), "nonfinite_inputs": 0,
            "has_motion": False, "has_defocus": False, "seconds": 0.01,
            **dict(zip(("scene_seed", "num_frames", "case", "kind", "nonfinite_expected"), _scene_facts(spec_json)))}


def _scene_facts(spec_json):
    """What the renderer's inputs part records of its loaded scene (``pipeline.render.inputs_part``)."""
    from scene_gen.cases import nonfinite_expected
    from scene_gen.spec import SceneSpec
    spec = SceneSpec.from_json(spec_json)
    return int(spec.seed), spec.num_frames, spec.case, spec.kind, nonfinite_expected(spec.case)


def fake_layers(spec_json, frame, render):
    W, H = render["res"]
    r = _rng(spec_json, frame, "layers")
    return {"layers": r.random((render["layer_levels"], H, W, 3), dtype=np.float32), "nonfinite_layers": 0,
            "seconds": 0.01}


def fake_reference(spec_json, frame, render):
    W, H = render["res"]
    r = _rng(spec_json, frame, "reference")
    return {"reference": r.random((H, W, 3), dtype=np.float32) + 0.5,
            "reference_stderr": np.full((H, W, 3), 0.01, np.float32), "reference_spp": render["ref_spp"],
            "reference_rel_stderr": 0.02, "nonfinite_reference": 0, "ref_time_slices": 1, "seconds": 0.01}


def fake_functions(reference=fake_reference):
    return SimpleNamespace(make_spec=fake_spec, render_inputs=fake_inputs, render_layers=fake_layers,
                           render_reference=reference, render_whole_frame=None, write_frame=tasks.write_frame)


class Flaky:
    """A reference function that fails: always for scene seed ``always``, on the first call for
    ``once``. Calls are counted in files under ``log`` (tasks are serialised, even in-process)."""

    def __init__(self, log: Path, always: int | None, once: int | None):
        self.log, self.always, self.once = Path(log), always, once
        self.log.mkdir(parents=True, exist_ok=True)

    def count(self, seed: int) -> int:
        p = self.log / str(seed)
        return len(p.read_text()) if p.exists() else 0

    @property
    def calls(self) -> dict[int, int]:
        return {int(p.name): len(p.read_text()) for p in self.log.iterdir()}

    def __call__(self, spec_json, frame, render):
        seed = json.loads(spec_json)["seed"]
        with open(self.log / str(seed), "a") as f:
            f.write("x")
        if seed == self.always:
            raise RuntimeError(f"renderer exploded on scene {seed}")
        if seed == self.once and self.count(seed) == 1:
            raise OSError("transient: worker lost its scratch disk")
        return fake_reference(spec_json, frame, render)


@pytest.fixture(scope="module")
def threaded_cluster():
    """An in-process cluster (threads), so the stand-in functions need no pickling by value."""
    from distributed import LocalCluster
    cl = LocalCluster(n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None,
                      protocol="tcp", host="127.0.0.1", silence_logs=logging.ERROR)
    yield cl
    cl.close()


# ---- graph structure -----------------------------------------------------------------------------
def test_keys_are_readable_and_grouped_by_stage():
    cfg = load_config(SMOKE)
    g = build_graph(cfg, "/tmp/s.zarr", token="")
    assert g.stages() == {"spec": 3, "inputs": 4, "layers": 4, "reference": 4, "write": 4}
    assert "reference-scene-000002/frame-1" in g.nodes and "spec-scene-000000" in g.nodes
    for k, n in g.nodes.items():
        assert key_split(k) == n.stage + "-scene"       # the dashboard groups tasks by stage
    w = g.nodes["write-scene-000002/frame-1"]
    assert w.dependencies == ("spec-scene-000002", "inputs-scene-000002/frame-1",
                              "layers-scene-000002/frame-1", "reference-scene-000002/frame-1")
    assert w.args[:4] == ("/tmp/s.zarr", 3, Ref("spec-scene-000002"), 1)   # store frame 3 = scene 2, frame 1
    assert w.kwargs == {"clip_id": cfg.frames()[3].clip_id}                 # the scene's balanced clip id
    assert g.writes == {0: "write-scene-000000/frame-0", 1: "write-scene-000001/frame-0",
                        2: "write-scene-000002/frame-0", 3: "write-scene-000002/frame-1"}
    keys = list(g.nodes)
    for k, n in g.nodes.items():                     # topological order
        assert all(keys.index(d) < keys.index(k) for d in n.dependencies)
    assert all(n.resources is None for n in g.nodes.values())


def test_subset_of_frames_unsplit_and_tokens():
    cfg = tiny_cfg(split_streams=False)
    frames = [f for f in cfg.frames() if f.index == 2]
    g = build_graph(cfg, "/a.zarr", frames)
    assert g.stages() == {"spec": 1, "render": 1, "write": 1}
    assert all(k.endswith("@" + g.token) for k in g.nodes) and len(g.token) == 8
    assert build_graph(cfg, "/b.zarr", frames).token != g.token          # other store, other keys
    assert build_graph(cfg, "/a.zarr", frames).token == g.token          # deterministic
    assert build_graph(cfg.with_cluster(workers=7), "/a.zarr", frames).token == g.token


def test_reference_resources_reach_the_scheduler(threaded_cluster, tmp_path):
    """Annotations must survive to the scheduler (they can be lost in graph optimisation): submit with
    {GPU: 1} to workers without GPUs; references wait unassigned, everything else runs."""
    from distributed import Client
    from stores.writer import open_or_create
    cfg = tiny_cfg(reference_resources={"GPU": 1})
    store = str(tmp_path / "t.zarr")                 # the spec tasks store each scene's JSON in it
    open_or_create(store, cfg.store_layout(), cfg.content_dict())
    g = build_graph(cfg, store, functions=fake_functions())
    refs = [k for k, n in g.nodes.items() if n.stage == "reference"]
    assert all(g.nodes[k].resources == {"GPU": 1} for k in refs)
    with Client(threaded_cluster, set_as_default=False) as c:
        futs = g.submit(c)
        for k, n in g.nodes.items():
            if n.stage in ("inputs", "layers"):
                futs[k].result(timeout=60)

        def restrictions(dask_scheduler, keys):
            return {k: (dict(dask_scheduler.tasks[k].resource_restrictions or {}), dask_scheduler.tasks[k].state)
                    for k in keys}
        got = c.run_on_scheduler(restrictions, keys=refs + list(g.writes.values()))
        c.cancel(list(futs.values()))
    for k in refs:
        assert got[k] == ({"GPU": 1}, "no-worker")
    for k in g.writes.values():
        assert got[k][0] == {} and got[k][1] == "waiting"


# ---- the CLI's run on stand-in functions: failures, retries, resume -------------------------------
def _complete(store) -> np.ndarray:
    return zarr.open_group(store, mode="r")["status/complete"][:]


def test_failing_frame_is_recorded_and_the_rest_completes(tmp_path, threaded_cluster, capfd):
    """The library's run (``pipeline.dataset.run_dataset``): a frame that keeps failing is recorded and
    the rest completes; a re-run redoes only it. The library prints nothing (the command prints)."""
    from pipeline.dataset import run_dataset
    cfg = tiny_cfg()
    fr = cfg.frames()
    flaky = Flaky(tmp_path / "calls1", always=fr[0].seed, once=fr[1].seed)            # scene 0 always fails; scene 1 once
    store = str(tmp_path / "t.zarr")
    s = run_dataset(cfg, out=store, scheduler=threaded_cluster.scheduler_address, progress=False,
                    functions=fake_functions(flaky))
    assert s["failed"].keys() == {0} and "renderer exploded" in s["failed"][0] and not s["ok"]
    assert flaky.calls[fr[0].seed] == 1 + cfg.tasks.retries                 # retried, then given up
    assert flaky.calls[fr[1].seed] == 2 + 1                  # 2 frames of the clip, one retry of the first
    assert list(_complete(store)) == [False, True, True]
    err = zarr.open_group(store, mode="r")["status/error"][:]
    assert "renderer exploded on scene" in str(err[0]) and str(err[1]) == ""
    assert s["validation"]["ok"] is False and any("frame 0: incomplete" in p for p in s["validation"]["problems"])
    # the written frames hold exactly what the tasks computed
    ref = zarr.open_group(store, mode="r")["reference/radiance"][1]
    spec1 = fake_spec(fr[1].seed, "outdoor", 2, (8, 4), {})
    want = fake_reference(spec1, 0, {"res": [8, 4], "ref_spp": 4})["reference"]
    np.testing.assert_array_equal(ref, want.transpose(2, 0, 1))

    # re-run: only the failed frame is redone, and now it works
    healthy = Flaky(tmp_path / "calls2", always=None, once=None)
    s2 = run_dataset(cfg, out=store, scheduler=threaded_cluster.scheduler_address, progress=False,
                     functions=fake_functions(healthy))
    assert s2["skipped"] == 2 and s2["rendered"] == 1 and s2["failed"] == {} and s2["ok"]
    assert healthy.calls == {fr[0].seed: 1}
    assert list(_complete(store)) == [True, True, True]
    assert str(zarr.open_group(store, mode="r")["status/error"][0]) == ""
    # nothing left to do: a third run renders nothing
    s3 = run_dataset(cfg, out=store, scheduler=threaded_cluster.scheduler_address, progress=False,
                     functions=fake_functions(healthy))
    assert s3["rendered"] == 0 and s3["skipped"] == 3 and s3["ok"] and healthy.calls == {fr[0].seed: 1}
    out = capfd.readouterr()
    assert out.out == "", out.out
    lines = []                                      # what it says, it says through say
    run_dataset(cfg, out=store, scheduler=threaded_cluster.scheduler_address, say=lines.append)
    assert len(lines) == 2 and lines[0].startswith("dataset ") and lines[0].endswith(f"-> {store}"), lines
    assert lines[1] == "resume: every frame is complete; nothing to render", lines


def test_store_from_another_config_is_refused_before_the_cluster(tmp_path, threaded_cluster):
    from pipeline.dataset import StoreMismatchError, run_dataset
    cfg = tiny_cfg()
    store = str(tmp_path / "t.zarr")
    run_dataset(cfg, out=store, scheduler=threaded_cluster.scheduler_address, progress=False,
                functions=fake_functions())
    other = cfg.with_overrides(seed=4)
    with pytest.raises(StoreMismatchError, match="different dataset config.*seed"):
        run_dataset(other, out=store, scheduler="tcp://127.0.0.1:1", progress=False)   # never connects
    assert _complete(store).all()


def test_default_functions_are_the_task_module():
    fn = default_functions()
    assert fn.render_reference is tasks.render_reference and fn.write_frame is tasks.write_frame
