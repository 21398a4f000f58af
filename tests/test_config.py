"""pipeline.config: the YAML dataset config is validated before anything runs (no rendering here)."""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.config import DatasetConfig, load_config
from pipeline.groups import scene_seed
from pipeline.errors import ConfigError

ROOT = Path(__file__).resolve().parent.parent
# dataset configs; configs/scaling-*.yaml are scaling studies, whose dataset configs tests/test_scaling.py checks
CONFIGS = sorted(p for p in (ROOT / "configs").glob("*.yaml") if not p.name.startswith("scaling-"))
SMOKE = ROOT / "configs" / "smoke.yaml"


def smoke_dict() -> dict:
    return yaml.safe_load(SMOKE.read_text())


def write(tmp_path, d) -> Path:
    p = tmp_path / "c.yaml"
    p.write_text(yaml.safe_dump(d))
    return p


@pytest.mark.parametrize("path", CONFIGS, ids=[p.name for p in CONFIGS])
def test_every_shipped_config_is_valid(path, real_scene_data):
    cfg = load_config(path)
    assert cfg.num_frames >= 1
    assert DatasetConfig.from_dict(cfg.to_dict()) == cfg


def test_shipped_configs_keep_the_papers_numbers():
    smoke = load_config(ROOT / "configs/smoke.yaml")
    assert (smoke.num_scenes, smoke.resolution, smoke.render_config().ref_spp) == (3, (16, 16), 64)
    assert sorted(g.frames for g in smoke.scenes) == [1, 1, 2]
    d = load_config(ROOT / "configs/default.yaml")
    rc = d.render_config()
    assert (rc.spp, rc.layer_levels, rc.ref_spp) == (8, 6, 4096)          # 8 spp, layers up to 32 spp
    assert {g.kind for g in d.scenes} == {"indoor", "outdoor"}
    assert {g.frames > 1 for g in d.scenes} == {True, False}               # stills and clips
    lp = load_config(ROOT / "configs/layer-paper.yaml")
    assert lp.num_frames == 4352 and lp.resolution == (256, 256)
    assert (lp.render_config().spp, lp.render_config().ref_spp) == (8, 4096)
    kinds = {k: sum(g.count * g.frames for g in lp.scenes if g.kind == k) for k in ("indoor", "outdoor")}
    assert kinds == {"indoor": 2176, "outdoor": 2176}                      # half indoor, half outdoor
    tp = load_config(ROOT / "configs/temporal-paper.yaml")
    assert {g.frames for g in tp.scenes} == {8} and 2 ** (tp.render_config().layer_levels - 1) == 32
    for c in (d, lp, tp):                       # references stop once converged to 3% (docs/training.md)
        assert c.render_config().ref_target_rel_stderr == 0.03 and c.render_config().ref_min_passes == 16


@pytest.mark.parametrize("edit, needle", [
    (lambda d: d.update(colour="red"), "unknown key(s) ['colour']"),
    (lambda d: d["render"].update(sppp=8), "unknown field(s) ['sppp']"),
    (lambda d: d["cluster"].update(wrokers=2), "dataset.cluster: unknown key(s) ['wrokers']"),
    (lambda d: d["scenes"][0].update(frame=2), "dataset.scenes[0]: unknown key(s) ['frame']"),
    (lambda d: d["tasks"].update(retry=1), "dataset.tasks: unknown key(s) ['retry']"),
    (lambda d: d.update(store={"codec": "zip"}), "dataset.store: unknown key(s) ['codec']"),
    (lambda d: d.update(resolution=-16), "dataset.resolution must be a positive int"),
    (lambda d: d.update(resolution=[16, 0]), "dataset.resolution"),
    (lambda d: d["scenes"][1].update(count=0), "dataset.scenes[1].count must be an integer in [1,"),
    (lambda d: d["scenes"][0].update(kind="space"), "dataset.scenes[0].kind must be one of"),
    (lambda d: d["scenes"][1].update(frames=-3), "dataset.scenes[1].frames"),
    (lambda d: d.update(scenes=[]), "dataset.scenes must be a non-empty list"),
    (lambda d: d.pop("scenes"), "dataset.scenes is required"),
    (lambda d: d["render"].update(spp=0), "render.spp must be an integer in [1, 4096]"),
    (lambda d: d["render"].update(oracle_spp=16), "dataset.render.oracle_spp must be 0"),
    (lambda d: d["render"].update(res=32), "dataset.render.res is not allowed"),
    (lambda d: d["scene_gen"].update(p_motion=1.5), "scene_gen.p_motion must be a probability in [0, 1]"),
    (lambda d: d.update(store={"feature_dtype": "int8"}), "dataset.store"),
    (lambda d: d["tasks"].update(retries=-1), "dataset.tasks.retries must be an integer in [0, 100]"),
    (lambda d: d["tasks"].update(reference_resources={"GPU": 0}), "dataset.tasks.reference_resources"),
    (lambda d: d["tasks"].update(split_streams=False, reference_resources={"GPU": 1}),
     "dataset.tasks.split_streams must be true when reference_resources is set"),
    (lambda d: d["cluster"].update(kind="kubernetes"), "dataset.cluster.kind must be one of"),
    (lambda d: d["cluster"].update(kind="scheduler"), "dataset.cluster.address must be a scheduler address"),
    (lambda d: d["cluster"].update(kind="slurm", jobqueue={"cores": 4}), "dataset.cluster.jobqueue.memory"),
    (lambda d: d["cluster"].update(workers=0), "dataset.cluster.workers"),
    (lambda d: d.update(seed=-1), "dataset.seed must be an integer in [0, 2**63)"),
    (lambda d: d.update(name="a/b"), "dataset.name"),
])
def test_bad_values_are_rejected_naming_the_field(tmp_path, edit, needle):
    d = smoke_dict()
    edit(d)
    with pytest.raises(ConfigError) as e:
        load_config(write(tmp_path, d))
    assert needle in str(e.value)
    assert str(tmp_path / "c.yaml") in str(e.value)      # the message names the file too


def test_unreadable_files_are_clear(tmp_path):
    with pytest.raises(ConfigError, match="does not exist"):
        load_config(tmp_path / "nope.yaml")
    p = tmp_path / "bad.yaml"
    p.write_text("scenes: [unclosed\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_config(p)
    p.write_text("- just\n- a list\n")
    with pytest.raises(ConfigError, match="dataset must be a mapping"):
        load_config(p)


def test_frames_order_and_seeds_follow_seedsequence():
    cfg = DatasetConfig.from_dict({"seed": 11, "scenes": [{"kind": "indoor", "count": 2},
                                                          {"kind": "outdoor", "count": 2, "frames": 3}]})
    fr = cfg.frames()
    assert [f.index for f in fr] == list(range(8)) and cfg.num_frames == 8 and cfg.num_scenes == 4
    assert [(f.scene, f.frame) for f in fr] == [(0, 0), (1, 0), (2, 0), (2, 1), (2, 2), (3, 0), (3, 1), (3, 2)]
    assert [f.kind for f in fr] == ["indoor"] * 2 + ["outdoor"] * 6
    # independent oracle: the seed is SeedSequence([root, scene]) and nothing else
    for f in fr:
        assert f.seed == int(np.random.SeedSequence([11, f.scene]).generate_state(1, np.uint32)[0] >> 1)
    assert len({f.seed for f in fr}) == 4                       # one seed per scene, frames of a clip share it
    assert fr[3].key == "scene-000002/frame-1" and fr[3].num_frames == 3
    other = DatasetConfig.from_dict({"seed": 12, "scenes": [{"kind": "indoor", "count": 2}]}).frames()
    assert other[0].seed != fr[0].seed and scene_seed(11, 0) == fr[0].seed


def test_store_path_rules(tmp_path, monkeypatch):
    cfg = load_config(SMOKE)
    monkeypatch.setenv("DENOISE_DATA", str(tmp_path / "d"))
    assert cfg.store_path() == str(tmp_path / "d" / "smoke.zarr")
    monkeypatch.delenv("DENOISE_DATA")
    assert cfg.store_path() == str(Path("data") / "smoke.zarr")
    assert cfg.store_path(str(tmp_path) + "/") == str(tmp_path / "smoke.zarr")
    assert cfg.store_path(str(tmp_path)) == str(tmp_path / "smoke.zarr")          # an existing folder
    assert cfg.store_path(str(tmp_path / "x.zarr")) == str(tmp_path / "x.zarr")
    assert cfg.store_path("s3://bucket/d.zarr") == "s3://bucket/d.zarr"
    monkeypatch.setenv("DENOISE_DATA", str(tmp_path))
    assert cfg.with_overrides(out="$DENOISE_DATA/y.zarr").store_path() == str(tmp_path / "y.zarr")


def test_content_dict_ignores_where_and_how_it_runs():
    cfg = load_config(SMOKE)
    other = cfg.with_cluster(workers=3, kind="scheduler", address="tcp://127.0.0.1:1").with_overrides(out="/x")
    assert other.content_dict() == cfg.content_dict()
    assert cfg.with_overrides(seed=8).content_dict() != cfg.content_dict()
    assert cfg.content_dict()["render"]["res"] == [16, 16]


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2 ** 40), w=st.integers(1, 512), h=st.integers(1, 512),
       groups=st.lists(st.tuples(st.sampled_from(["indoor", "outdoor"]), st.integers(1, 5), st.integers(1, 9)),
                       min_size=1, max_size=4),
       retries=st.integers(0, 5), workers=st.none() | st.integers(1, 64))
def test_round_trip_and_frame_count(seed, w, h, groups, retries, workers):
    d = {"seed": seed, "resolution": [w, h], "scenes": [{"kind": k, "count": c, "frames": f} for k, c, f in groups],
         "tasks": {"retries": retries}, "cluster": {"workers": workers}, "render": {"ref_spp": 64, "ref_passes": 16}}
    cfg = DatasetConfig.from_dict(d)
    back = DatasetConfig.from_dict(yaml.safe_load(yaml.safe_dump(cfg.to_dict())))
    assert back == cfg
    assert cfg.num_frames == sum(c * f for _, c, f in groups) == len(cfg.frames())
    lay = cfg.store_layout()
    assert (lay.num_frames, lay.height, lay.width, lay.spp, lay.layer_spp) == (cfg.num_frames, h, w, 8,
                                                                               (1, 2, 4, 8, 16, 32))


def test_cli_rejects_bad_config_before_rendering(tmp_path, capsys):
    from pipeline.__main__ import main
    d = smoke_dict()
    d["resolution"] = -16
    out = tmp_path / "never.zarr"
    t0 = time.perf_counter()
    rc = main(["dataset", "--config", str(write(tmp_path, d)), "--out", str(out)])
    err = capsys.readouterr().err
    assert rc == 2 and "dataset.resolution must be a positive int" in err and "-16" in err
    assert not out.exists() and time.perf_counter() - t0 < 10
    d = smoke_dict()
    d["scene_gen"]["outdoor_objectz"] = 3
    assert main(["dataset", "--config", str(write(tmp_path, d)), "--out", str(out)]) == 2
    assert "outdoor_objectz" in capsys.readouterr().err and not out.exists()


def test_cli_unreachable_scheduler_fails_fast(tmp_path, capsys):
    import socket
    from pipeline.__main__ import main
    with socket.socket() as s:                      # a loopback port that nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    d = smoke_dict()
    d["cluster"]["connect_timeout"] = 2
    out = tmp_path / "never.zarr"
    t0 = time.perf_counter()
    rc = main(["dataset", "--config", str(write(tmp_path, d)), "--out", str(out),
               "--scheduler", f"tcp://127.0.0.1:{port}"])
    err = capsys.readouterr().err
    assert rc == 2 and f"cannot reach the Dask scheduler at tcp://127.0.0.1:{port}" in err
    assert not out.exists()                          # nothing created, nothing rendered
    assert time.perf_counter() - t0 < 20


def test_split_fractions_reach_the_store_reader(tmp_path):
    import yaml
    from pipeline.config import load_config
    p = tmp_path / "c.yaml"
    p.write_text(yaml.safe_dump({"name": "s", "scenes": [{"kind": "indoor", "count": 2}],
                                 "split": {"train": 0.5, "val": 0.0, "test": 0.5}}))
    cfg = load_config(p)
    assert cfg.content_dict()["split"] == {"train": 0.5, "val": 0.0, "test": 0.5}
    assert load_config(p).to_dict() == cfg.to_dict()
    p.write_text(yaml.safe_dump({"name": "s", "scenes": [{"kind": "indoor", "count": 2}], "split": {"train": -1}}))
    with pytest.raises(ConfigError, match="dataset.split"):
        load_config(p)


def test_scene_kinds_and_store_keys_have_one_source():
    from pipeline import config as C
    from pipeline import groups as Gr
    from scene_gen.families import family_names
    from stores.schema import SHAPE_FIELDS, StoreLayout
    assert Gr.family_names is family_names           # the registry's, asked at each check
    assert C.STORE_KEYS == {"tile", "radiance_encoding", "feature_dtype", "encoding"}
    assert C.STORE_KEYS | set(SHAPE_FIELDS) == set(StoreLayout.__dataclass_fields__)


def test_split_streams_default_follows_reference_resources(tmp_path):
    """``tasks.split_streams`` null (the default): one task a frame, unless references need their own
    workers; an explicit true or false wins; anything else is refused."""
    from pipeline.graph import build_graph
    d = smoke_dict()
    d["tasks"].pop("split_streams", None)
    cfg = load_config(write(tmp_path, d))
    assert cfg.tasks.split_streams is None and cfg.tasks.split is False
    assert {n.stage for n in build_graph(cfg, "s.zarr").nodes.values()} == {"spec", "render", "write"}
    d["tasks"]["reference_resources"] = {"GPU": 1}
    cfg = load_config(write(tmp_path, d))
    assert cfg.tasks.split is True
    g = build_graph(cfg, "s.zarr")
    assert {n.stage for n in g.nodes.values()} == {"spec", "inputs", "layers", "reference", "write"}
    assert all(n.resources == {"GPU": 1} for n in g.nodes.values() if n.stage == "reference")
    d["tasks"] = {"split_streams": True}
    assert load_config(write(tmp_path, d)).tasks.split is True
    d["tasks"] = {"split_streams": "yes"}
    with pytest.raises(ConfigError, match="dataset.tasks.split_streams must be true, false or null"):
        load_config(write(tmp_path, d))


def test_a_batch_jobs_memory_is_shared_by_the_workers_it_will_run():
    """Without ``processes``, a job runs ``cores / threads_per_worker`` workers (pipeline.jobs.job_settings),
    so the memory check before submitting divides the job's memory by that many."""
    from pipeline.config import ClusterConfig, worker_memory
    c = ClusterConfig(kind="slurm", jobqueue={"cores": 8, "memory": "32GiB"})
    assert worker_memory(c)[0] == 4 * 2 ** 30
    c = ClusterConfig(kind="slurm", threads_per_worker=2, jobqueue={"cores": 8, "memory": "32GiB"})
    assert worker_memory(c)[0] == 8 * 2 ** 30
    c = ClusterConfig(kind="pbs", jobqueue={"cores": 8, "processes": 2, "memory": "32GiB"})
    assert worker_memory(c)[0] == 16 * 2 ** 30


def test_the_shared_checks_name_the_setting_in_one_line():
    """core.checks, behind every config: '<name> must be <allowed>, got <value>' in the caller's error
    class; bools are not integers or numbers; numpy integers only where asked for."""
    from core.checks import is_int, is_number, known_keys, need, need_int
    with pytest.raises(ConfigError, match=r"^render\.spp must be an integer in \[1, 4096\], got 0$"):
        need_int("render.spp", 0, 1, 4096, ConfigError)
    with pytest.raises(ConfigError, match=r"^x must be an integer >= 1, got True$"):
        need_int("x", True, 1, None, ConfigError)
    need_int("x", np.int64(3), 1, None, ConfigError, numpy=True)
    assert not is_int(np.int64(3)) and is_int(np.int64(3), numpy=True) and not is_int(True, numpy=True)
    assert is_number(2) and is_number(0.5) and not is_number(True) and not is_number(float("nan"), finite=True)
    need(True, "never", "raised", 0, ConfigError)
    with pytest.raises(ConfigError, match=r"^a\.b must be one of \('u', 'v'\), got 'w'$"):
        need(False, "a.b", "one of ('u', 'v')", "w", ConfigError)
    assert known_keys(None, ["a"], "s", ConfigError) == {}
    with pytest.raises(ConfigError, match=r"^s: unknown key\(s\) \['c'\]; known: \['a', 'b'\]$"):
        known_keys({"a": 1, "c": 2}, ["b", "a"], "s", ConfigError)
    with pytest.raises(ConfigError, match=r"^s must be a mapping, got list$"):
        known_keys([1], ["a"], "s", ConfigError)
