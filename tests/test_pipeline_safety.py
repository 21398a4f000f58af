"""``python -m pipeline dataset`` never loses what is not its own, and never leaves a store no re-run takes.

Real folders, real stores, real processes: a folder that is not a store is refused and left byte for
byte; a second run on a store is refused while the first lives (it is paused inside store creation by
``procs.pause_at`` its creation seam), then the first is SIGKILLed there and the next run takes over its lock,
makes the half-created store again and finishes it; a shard file deleted from a complete frame makes
the next run render that frame again. Plus the config checks that stop a run before anything starts,
and the split assignment that gives small configs val and test scenes.
"""
from __future__ import annotations

import hashlib
import json
import os
import re
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from pipeline.config import DatasetConfig, load_config
from pipeline.errors import ConfigError
from stores import create, schema
from stores.errors import ForeignStoreError, IncompleteStoreError, StoreExistsError, StoreLockedError
from stores.lock import StoreLock
from stores.schema import LOCK_NAME
from stores.schema import StoreLayout
from stores.writer import open_or_create

from procs import kill_group, pause_at, python_m

ROOT = Path(__file__).resolve().parent.parent
SMOKE = ROOT / "configs" / "smoke.yaml"
# dataset configs; configs/scaling-*.yaml are scaling studies, whose dataset configs tests/test_scaling.py checks
CONFIGS = sorted(p for p in (ROOT / "configs").glob("*.yaml") if not p.name.startswith("scaling-"))
PY = sys.executable
CREATION = "stores.create:_creation_hook"    # the seam inside store creation where a test pauses a run
TINY = StoreLayout(num_frames=2, height=8, width=8, spp=2, layer_spp=(1, 2), tile=8)



def read_lock(store) -> dict | None:
    """The lock record in ``store`` (None if there is none or it is unreadable)."""
    try:
        with open(os.path.join(os.fspath(store), LOCK_NAME)) as f:
            d = json.load(f)
        return d if isinstance(d, dict) else None
    except (OSError, ValueError):
        return None


def _env(**extra) -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    env["PYTHONUNBUFFERED"] = "1"
    env.update(extra)
    return env


def _cli(out: Path, *extra: str, summary: Path | None = None, hook: str = "") -> list[str]:
    cmd = [*python_m("pipeline", hook), "dataset", "--config", str(SMOKE), "--out", str(out), "--no-progress"]
    return cmd + (["--summary-json", str(summary)] if summary else []) + list(extra)


def _tree(path: Path) -> dict[str, str]:
    """Every file under ``path`` -> sha1 of its bytes (what must survive untouched)."""
    return {str(p.relative_to(path)): hashlib.sha1(p.read_bytes()).hexdigest()
            for p in sorted(path.rglob("*")) if p.is_file()}


# ---- 1. never delete a folder that is not ours ---------------------------------------------------
def _foreign_folders(tmp_path: Path) -> dict[str, Path]:
    plain = tmp_path / "plain.zarr"
    (plain / "sub").mkdir(parents=True)
    (plain / "thesis.tex").write_text("years of work")
    (plain / "sub" / "data.bin").write_bytes(os.urandom(64))
    v2 = tmp_path / "v2.zarr"                     # a Zarr v2 store: .zgroup, an array with .zarray + a chunk
    (v2 / "a").mkdir(parents=True)
    (v2 / ".zgroup").write_text('{"zarr_format": 2}')
    (v2 / "a" / ".zarray").write_text('{"zarr_format": 2, "shape": [2], "chunks": [2], "dtype": "<f4"}')
    (v2 / "a" / "0").write_bytes(b"\0" * 8)
    headless = tmp_path / "headless.zarr"         # one of our stores that lost its root zarr.json
    create.create_store(headless, TINY, {"x": 1})
    (headless / "zarr.json").unlink()
    return {"plain": plain, "v2": v2, "headless": headless}


def test_cli_refuses_a_folder_that_is_not_a_store_and_leaves_it_alone(tmp_path, capsys):
    from pipeline.__main__ import main
    for name, folder in _foreign_folders(tmp_path).items():
        before = _tree(folder)
        rc = main(["dataset", "--config", str(SMOKE), "--out", str(folder), "--no-progress"])
        err = capsys.readouterr().err
        assert rc == 2, (name, err)
        assert f"{folder} is a non-empty folder that is not a store" in err and "--overwrite" in err, err
        assert _tree(folder) == before, f"{name}: the folder was changed"
    f = tmp_path / "a-file.zarr"
    f.write_text("not a folder")
    assert main(["dataset", "--config", str(SMOKE), "--out", str(f), "--no-progress"]) == 2
    assert "is a file, not a folder" in capsys.readouterr().err and f.read_text() == "not a folder"


def test_out_that_cannot_be_made_is_a_one_line_error(tmp_path, capsys):
    """--out under a file, or somewhere the file system refuses (/sys is read-only even for root)."""
    from pipeline.__main__ import main
    f = tmp_path / "afile"
    f.write_text("a file")
    outs = [f / "x.zarr", f / "sub" / "x.zarr"]
    if _sys_read_only():
        outs += [Path("/sys/denoise-test.zarr"), Path("/sys/denoise-test/sub/x.zarr")]
    for out in outs:
        rc = main(["dataset", "--config", str(SMOKE), "--out", str(out), "--no-progress"])
        err = capsys.readouterr().err
        assert rc == 2 and err.startswith("error: ") and "Traceback" not in err, (out, err)
        assert str(out) in err and "choose another" in err, err
    assert f.read_text() == "a file"
    from stores.errors import StorePathError
    with pytest.raises(StorePathError, match=f"store path {f}/x.zarr: cannot make the store's folder"):
        StoreLock(f / "x.zarr").acquire()


def _sys_read_only() -> bool:
    if not os.path.isdir("/sys"):
        return False
    try:
        os.mkdir("/sys/denoise-probe")
    except OSError:
        return True
    os.rmdir("/sys/denoise-probe")
    return False


def test_library_refuses_foreign_folders_and_existing_stores_unless_overwrite(tmp_path):
    folders = _foreign_folders(tmp_path)
    for folder in folders.values():
        before = _tree(folder)
        with pytest.raises(ForeignStoreError, match="non-empty folder that is not a store"):
            create.create_store(folder, TINY)
        with pytest.raises(ForeignStoreError):
            open_or_create(folder, TINY)
        assert _tree(folder) == before
    w = open_or_create(folders["plain"], TINY, {"new": True}, overwrite=True)      # opted in: replaced
    assert w.num_frames == 2 and not (folders["plain"] / "thesis.tex").exists()
    with pytest.raises(StoreExistsError, match="already exists"):
        create.create_store(folders["plain"], TINY)
    assert schema.store_exists(folders["plain"]) and create.foreign_entries(folders["plain"]) is None
    empty = tmp_path / "empty.zarr"
    empty.mkdir()
    create.create_store(empty, TINY)                              # an empty folder is a fine place
    # URLs: only "not found" means no store
    assert schema.store_exists(f"file://{folders['plain']}") and not schema.store_exists(f"file://{tmp_path}/none.zarr")


# ---- 7. one writer per store ---------------------------------------------------------------------
_HOLD = ("import sys, time; from stores.lock import StoreLock; l = StoreLock(sys.argv[1], command='holder').acquire();"
         " print('locked', flush=True); time.sleep(120)")


def test_lock_refuses_a_live_holder_and_takes_over_from_a_dead_one(tmp_path):
    store = tmp_path / "s.zarr"
    p = subprocess.Popen([PY, "-c", _HOLD, str(store)], env=_env(), cwd=ROOT, stdout=subprocess.PIPE, text=True,
                         start_new_session=True)
    try:
        assert p.stdout.readline().strip() == "locked"
        with pytest.raises(StoreLockedError) as e:
            StoreLock(store).acquire()
        msg = str(e.value)
        assert f"pid {p.pid} on host {socket.gethostname()}, started 20" in msg and "(holder)" in msg
        assert e.value.holder["pid"] == p.pid
    finally:
        kill_group(p)                                     # dies holding it: the file stays behind
    assert read_lock(store)["pid"] == p.pid
    with StoreLock(store) as lock:
        assert lock.took_over["pid"] == p.pid and read_lock(store)["pid"] == os.getpid()
    assert read_lock(store) is None                        # released: the file is gone


def test_lock_refuses_records_it_cannot_prove_dead(tmp_path):
    store = tmp_path / "s.zarr"
    store.mkdir()
    sleeper = subprocess.Popen(["sleep", "60"])
    try:       # a live pid on this host that holds no flock (e.g. an old run): not taken over
        (store / schema.LOCK_NAME).write_text(json.dumps({"host": socket.gethostname(), "pid": sleeper.pid,
                                                          "started": "2026-01-01T00:00:00Z"}))
        with pytest.raises(StoreLockedError, match=f"pid {sleeper.pid}.*delete the lock file"):
            StoreLock(store).acquire()
    finally:
        sleeper.kill()
        sleeper.wait()
    (store / schema.LOCK_NAME).write_text(json.dumps({"host": "elsewhere-node-7", "pid": 1,
                                                      "started": "2026-01-01T00:00:00Z"}))
    with pytest.raises(StoreLockedError, match="host elsewhere-node-7.*another host"):
        StoreLock(store).acquire()


def test_pid_alive_is_false_for_pids_that_are_not_one_process():
    from stores.procinfo import pid_alive
    for pid in (0, -1, -12345, None):               # os.kill(0 / -1, 0) would signal a group / everything
        assert pid_alive(pid) is False, pid
    assert pid_alive(os.getpid()) and pid_alive(os.getpid(), proc_start=None)


# ---- 7 + 8 + 2 + 10 end to end: concurrent run refused, kill inside creation, resume, lost shard ---
@pytest.fixture(scope="module")
def killed_in_creation(tmp_path_factory):
    """Run A (``--overwrite`` on a folder holding a stray file) pauses inside store creation (holding the
    lock); run B is started meanwhile; A is SIGKILLed there; run C is the plain command again. Returns
    their outputs and the store."""
    d = tmp_path_factory.mktemp("create")
    out, flag = d / "smoke.zarr", d / "paused"
    out.mkdir()
    (out / "stray.txt").write_text("not a store")
    a = subprocess.Popen(_cli(out, "--overwrite", hook=pause_at(CREATION, flag)), env=_env(), cwd=ROOT,
                         start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        t0 = time.monotonic()
        while not flag.exists() and a.poll() is None and time.monotonic() - t0 < 180:
            time.sleep(0.2)
        assert flag.exists(), "run A never reached the creation pause"
        b = subprocess.run(_cli(out), env=_env(), cwd=ROOT, capture_output=True, text=True, timeout=120)
        half = {"zarr.json": json.loads((out / "zarr.json").read_text()), "lock": read_lock(out),
                "stray": (out / "stray.txt").exists()}
    finally:
        kill_group(a)
    c = subprocess.run(_cli(out, summary=d / "c.json"), env=_env(), cwd=ROOT, capture_output=True, text=True,
                       timeout=600)
    return {"out": out, "a": a, "b": b, "half": half, "c": c, "dir": d,
            "c_summary": json.loads((d / "c.json").read_text()) if (d / "c.json").exists() else None}


def test_second_run_is_refused_while_the_first_holds_the_store(killed_in_creation):
    b, a = killed_in_creation["b"], killed_in_creation["a"]
    assert b.returncode == 2, b.stdout[-2000:] + b.stderr[-2000:]
    assert (f"is in use by another dataset run: pid {a.pid} on host {socket.gethostname()}, started 20"
            in b.stderr), b.stderr
    assert "dashboard" not in b.stdout                     # refused before a cluster was started


def test_kill_inside_creation_leaves_a_store_the_next_run_finishes(killed_in_creation):
    half, c, s = killed_in_creation["half"], killed_in_creation["c"], killed_in_creation["c_summary"]
    assert half["zarr.json"]["attributes"]["creating"]["pid"] == killed_in_creation["a"].pid   # really half-made
    assert half["lock"]["pid"] == killed_in_creation["a"].pid
    assert not half["stray"]                                         # --overwrite cleared the folder first
    assert c.returncode == 0, c.stdout[-3000:] + c.stderr[-3000:]
    assert f"took over the lock of a dead run (pid {killed_in_creation['a'].pid}" in c.stdout
    assert s["complete"] == 4 and s["rendered"] == 4 and s["ok"] and s["validation"]["ok"]
    assert read_lock(killed_in_creation["out"]) is None            # released at the end
    root, _ = schema.open_group(killed_in_creation["out"])          # no IncompleteStoreError any more
    assert "creating" not in dict(root.attrs)


def test_smoke_store_has_train_val_and_test_scenes(killed_in_creation):
    from stores.reader import open_store
    st = open_store(killed_in_creation["out"])
    cfg = load_config(SMOKE)
    got = {sp: st.frames_in_split(sp) for sp in ("train", "val", "test")}
    assert all(got.values()), got                                  # `make train` finds val and test frames
    assert [st.split_of_frame(f.index) for f in cfg.frames()] == [cfg.scene_splits()[f.scene] for f in cfg.frames()]
    assert got["train"] == [2, 3]                                  # the clip trains


def test_resume_renders_a_complete_frame_again_when_a_shard_file_is_lost(killed_in_creation):
    out, d = killed_in_creation["out"], killed_in_creation["dir"]
    assert killed_in_creation["c"].returncode == 0
    shard = sorted((out / "inputs" / "radiance" / "c" / "1").rglob("*"))
    shard = [p for p in shard if p.is_file()][0]
    others = {str(p): p.stat().st_mtime_ns for p in (out / "inputs" / "radiance" / "c").rglob("*")
              if p.is_file() and p != shard}
    shard.unlink()                                                 # frame 1 is marked complete, its data is gone
    r = subprocess.run(_cli(out, summary=d / "d.json"), env=_env(), cwd=ROOT, capture_output=True, text=True,
                       timeout=600)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    s = json.loads((d / "d.json").read_text())
    assert s["rendered"] == 1 and s["skipped"] == 3 and s["complete"] == 4 and s["validation"]["ok"], s
    assert shard.exists()
    assert {p: os.stat(p).st_mtime_ns for p in others} == others   # the other frames were not rewritten
    from stores.validate import validate_store
    assert validate_store(str(out)).ok


def test_resume_renders_a_frame_again_when_its_completion_flag_is_damaged(killed_in_creation):
    """A flipped byte in the ``status/complete`` chunk (schema v3: one chunk holds 1024 frames' flags):
    the next run re-renders the frames of that chunk (no traceback from the pre-flight store check)."""
    out, d = killed_in_creation["out"], killed_in_creation["dir"]
    assert killed_in_creation["c"].returncode == 0
    flag = out / "status" / "complete" / "c" / "0"
    data = bytearray(flag.read_bytes())
    data[0] ^= 0x01                                                # fails its crc32c
    flag.write_bytes(bytes(data))
    r = subprocess.run(_cli(out, summary=d / "f.json"), env=_env(), cwd=ROOT, capture_output=True, text=True,
                       timeout=600)
    assert r.returncode == 0 and "Traceback" not in r.stderr, r.stdout[-3000:] + r.stderr[-3000:]
    s = json.loads((d / "f.json").read_text())
    assert s["rendered"] == 4 and s["complete"] == 4 and s["validation"]["ok"], s
    from stores.reader import open_store
    assert open_store(out).complete_frames() == [0, 1, 2, 3]


# ---- 8: a half-created store from the library's side ---------------------------------------------
def test_half_created_store_is_named_and_made_again(tmp_path):
    store = tmp_path / "h.zarr"
    flag = tmp_path / "flag"
    code = (pause_at(CREATION, flag) + "\nimport sys; from stores import create; from stores.schema import StoreLayout; "
            "create.create_store(sys.argv[1], StoreLayout(num_frames=2, height=8, width=8, spp=2, "
            "layer_spp=(1, 2), tile=8))")
    p = subprocess.Popen([PY, "-c", code, str(store)], env=_env(), cwd=ROOT,
                         start_new_session=True)
    try:
        t0 = time.monotonic()
        while not flag.exists() and time.monotonic() - t0 < 60:
            time.sleep(0.1)
        assert flag.exists()
        with pytest.raises(StoreLockedError, match=f"being created by pid {p.pid}"):   # alive: hands off
            open_or_create(store, TINY)
    finally:
        kill_group(p)
    with pytest.raises(IncompleteStoreError, match=f"creation by pid {p.pid} .* was cut short"):
        schema.open_group(store)
    w = open_or_create(store, TINY, {"again": True})
    assert w.num_frames == 2 and w.incomplete_frames() == [0, 1]
    assert dict(schema.open_group(store)[0].attrs)["config"] == {"again": True}


def test_half_created_store_whose_pid_was_reused_is_made_again(tmp_path):
    """The creation record's pid now belongs to a later process (its start time differs): not the
    creator, so the store is made again; the same pid with its own start time still hands off."""
    import zarr
    from stores.procinfo import process_start
    store = tmp_path / "r.zarr"
    create.create_store(store, TINY)
    sleeper = subprocess.Popen(["sleep", "60"])
    try:
        real = process_start(sleeper.pid)
        root = zarr.open_group(str(store), mode="r+")
        for start, reused in ((real, False), (real - 1, True)):
            root.attrs["creating"] = {"host": socket.gethostname(), "pid": sleeper.pid, "proc_start": start,
                                      "started": "2026-01-01T00:00:00Z"}
            if reused:
                w = open_or_create(store, TINY, {"again": True})
                assert w.num_frames == 2 and "creating" not in dict(schema.open_group(store)[0].attrs)
            else:
                with pytest.raises(StoreLockedError, match=f"being created by pid {sleeper.pid}"):
                    open_or_create(store, TINY)
    finally:
        sleeper.kill()
        sleeper.wait()
    assert isinstance(dict(schema.open_group(store)[0].attrs).get("config"), dict)


# ---- 8, 15: config checks that stop a run before anything starts ---------------------------------
def _smoke() -> dict:
    return yaml.safe_load(SMOKE.read_text())


@pytest.mark.parametrize("levels", [0, 13, -1, 2.5])
def test_layer_levels_out_of_range_is_refused_with_one_range(levels):
    d = _smoke()
    d["render"]["layer_levels"] = levels
    with pytest.raises(ConfigError, match=r"dataset.render.layer_levels must be an integer in \[1, 12\]"):
        DatasetConfig.from_dict(d)


def test_config_path_errors_say_what_is_wrong(tmp_path):
    with pytest.raises(ConfigError, match="is a directory, not a YAML file"):
        load_config(tmp_path)
    with pytest.raises(ConfigError, match="does not exist"):
        load_config(tmp_path / "nope.yaml")
    p = tmp_path / "dup.yaml"
    p.write_text(SMOKE.read_text() + "seed: 8\n")
    with pytest.raises(ConfigError, match=r"duplicate key 'seed' \(line \d+, first on line \d+\)"):
        load_config(p)
    p.write_text("name: x\nscenes: [{kind: indoor, count: 1, count: 2}]\n")
    with pytest.raises(ConfigError, match="duplicate key 'count'"):
        load_config(p)


def test_yaml_merge_keys_may_be_overridden_but_not_repeated(tmp_path):
    p = tmp_path / "merge.yaml"
    p.write_text("name: merged\nscenes: [&b {kind: indoor, count: 1, frames: 2}, {<<: *b, count: 3}]\n")
    assert [(g.count, g.frames) for g in load_config(p).scenes] == [(1, 2), (3, 2)]
    from pipeline.config import _unique_key_loader
    data = yaml.load("b: &b {kind: indoor, count: 1, frames: 2}\nx: [{<<: *b, count: 3}, {<<: *b}]\n",
                     Loader=_unique_key_loader())
    assert data["x"] == [{"kind": "indoor", "count": 3, "frames": 2}, {"kind": "indoor", "count": 1, "frames": 2}]
    p.write_text("x: &b {a: 1}\ny: {<<: *b, a: 2, a: 3}\n")        # the node's own keys twice: refused
    with pytest.raises(ConfigError, match="duplicate key 'a'"):
        load_config(p)


def test_a_frame_that_cannot_fit_in_memory_is_refused(tmp_path, capsys):
    """Refused before a cluster starts where the run's workers are known (a LocalCluster, batch jobs),
    whatever this machine's memory; a config loads (it may be for a remote cluster)."""
    from pipeline.__main__ import main
    from pipeline.dataset import check_memory_before_start
    d = _smoke()
    d["resolution"] = 16384
    cfg16k = DatasetConfig.from_dict(d)                         # valid: it may run on a bigger cluster
    check_memory_before_start(cfg16k, scheduler="tcp://127.0.0.1:1")   # checked there once connected
    d["cluster"] = {**d["cluster"], "memory_limit": "64GiB"}
    p = tmp_path / "big.yaml"
    p.write_text(yaml.safe_dump(d))
    rc = main(["dataset", "--config", str(p), "--out", str(tmp_path / "big.zarr"), "--no-progress"])
    out = capsys.readouterr()
    assert rc == 2 and "dashboard" not in out.out, out.out + out.err          # refused before a cluster
    assert re.search(r"16384x16384 cannot be rendered: one frame needs about \d+\.\d GiB \([\d,]+ bytes: .*"
                     r"a worker has 64\.0 GiB \(cluster\.memory_limit 64GiB\)", out.err), out.err
    assert not (tmp_path / "big.zarr").exists()
    with pytest.raises(ConfigError, match=r"a worker has \d+\.\d GiB \(this machine's \d+\.\d GiB over 3 worker\(s\)\)"):
        check_memory_before_start(cfg16k.with_cluster(workers=5), workers=3)     # --workers wins
    from pipeline.config import frame_bytes
    cfg = load_config(SMOKE)
    big = cfg.with_cluster(memory_limit="1PiB").with_overrides(resolution=(16384, 16384))   # fits a 1 PiB worker
    assert frame_bytes(big) > 170e9                                                  # the issue's ~170 GB
    with pytest.raises(ConfigError, match=r"16x16 cannot be rendered.*a worker has 97.7 KiB \(the test's\)"):
        cfg.check_memory(per_worker=100_000, where="the test's")
    cfg.check_memory(per_worker=2 ** 30)


# ---- 10: every small config puts scenes in val and test ------------------------------------------
@pytest.mark.parametrize("path", CONFIGS, ids=[p.name for p in CONFIGS])
def test_splits_are_balanced_and_read_back_by_the_store_rule(path, real_scene_data):
    from stores.reader import split_of_clip
    cfg = load_config(path)
    fr = cfg.split_fractions
    ids, splits = cfg.scene_clip_ids(), cfg.scene_splits()
    assert len(set(ids)) == len(ids)                                # clip ids stay distinct
    assert splits == [split_of_clip(c, fr) for c in ids]
    positive = [k for k, v in fr.items() if v > 0]
    if cfg.num_scenes >= len(positive):
        assert {k for k in positive if splits.count(k) == 0} == set()
    raised = sum(1 for k in positive if cfg.num_scenes * fr[k] / sum(fr.values()) < 0.5)   # lifted to one scene
    for k in positive:                                               # else within one scene of the fraction
        assert abs(splits.count(k) - cfg.num_scenes * fr[k] / sum(fr.values())) <= 1 + raised


def test_store_made_before_clip_ids_resumes_with_its_old_split(tmp_path):
    from pipeline.dataset import check_existing_store
    cfg = load_config(SMOKE)
    legacy = cfg.with_overrides(clip_ids="scene_seed")
    assert "clip_ids" not in legacy.content_dict() and cfg.content_dict()["clip_ids"] == "balanced"
    store = str(tmp_path / "old.zarr")
    open_or_create(store, cfg.store_layout(), json.loads(json.dumps(legacy.content_dict())))
    run_cfg = check_existing_store(cfg, store)
    assert run_cfg.clip_ids == "scene_seed"
    assert [f.clip_id for f in run_cfg.frames()] == [f.seed for f in cfg.frames()]


def test_a_store_with_damaged_array_metadata_is_refused_and_overwrite_replaces_it(tmp_path):
    """Array metadata that disagrees with the schema (e.g. a store written with another codec chain) is
    damage: the run stops naming it, and ``--overwrite`` (which deletes whatever is there) rebuilds."""
    from pipeline.dataset import check_existing_store
    from stores.errors import StoreCorruptionError
    cfg = load_config(SMOKE)
    store = tmp_path / "s.zarr"
    open_or_create(str(store), cfg.store_layout(), cfg.content_dict())
    meta = store / "reference" / "radiance" / "zarr.json"
    m = json.loads(meta.read_text())
    m["fill_value"] = 1.0                                     # no longer what the schema writes
    meta.write_text(json.dumps(m))
    with pytest.raises(StoreCorruptionError, match="disagrees with schema"):
        check_existing_store(cfg, str(store))
    assert check_existing_store(cfg, str(store), overwrite=True) is cfg
    w = open_or_create(str(store), cfg.store_layout(), cfg.content_dict(), overwrite=True)
    assert w.num_frames == cfg.num_frames
    check_existing_store(cfg, str(store))                     # made again: nothing to refuse
