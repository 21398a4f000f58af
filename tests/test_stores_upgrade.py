"""Older stores through one door (``stores.upgrade``): a store of each older schema version, made by the
code that wrote it (the repository's own history: the last commit that wrote v1, and the last that wrote
v2, run in a subprocess), upgraded by ``python -m stores upgrade``, reads back equal array by array to
what that code's own reader reads from the original. Readers and writers refuse older versions with a
line naming ``upgrade``; an upgrade stopped anywhere is finished by running it again."""
from __future__ import annotations

import io
import os
import pickle
import shutil
import subprocess
import sys
import tarfile
from pathlib import Path

import numpy as np
import pytest

from stores.upgrade import migrate as upgrade
from stores.contract import FRAME_META
from stores.errors import SchemaVersionError
from stores.reader import open_store
from stores.schema import ARRAY_BY_PATH, ARRAY_BY_SOURCE, SCHEMA_VERSION, meta_path

ROOT = Path(__file__).resolve().parents[1]
# the last commits whose create_store wrote each older version (the next one brought the new version)
WRITERS = {1: "9b3a4b1~1", 2: "3e57252~1"}
FRAMES = 6          # a 3-frame moving clip, a 2-frame clip, a failed frame at the end

WRITE = r'''
import pickle, sys
sys.path.insert(0, sys.argv[1] + "/tests")
import numpy as np
from stores import writer
from stores.reader import open_store
from stores.schema import StoreLayout
from test_stores_synthetic import synthetic_frame
out, dump = sys.argv[2], sys.argv[3]
lay = StoreLayout(num_frames=6, height=16, width=16, spp=4, layer_spp=(1, 2), tile=8)
w = writer.open_or_create(out, lay, {"seed": 1, "made_by": "old"})
clips = [(11, 0, 3), (11, 1, 3), (11, 2, 3), (12, 0, 2), (12, 1, 2)]
for i, (seed, k, n) in enumerate(clips):
    f = synthetic_frame(seed=seed, h=16, w=16, spp=4, frame=k, num_frames=n, motion=(seed == 11))
    f["layers"] = f["layers"][:2]
    w.write_frame(i, f)
w.mark_failed(5, RuntimeError("the renderer ran out of memory"))
s = open_store(out)
images = [k for k in ("radiance", "features", "layers", "reference", "reference_stderr", "guides_albedo",
                      "guides_normal", "guides_depth", "guides_motion")]
read = {"complete": [int(i) for i in s.complete_frames()], "incomplete": [int(i) for i in s.incomplete_frames()],
        "errors": {i: str(s.frames_meta(i)["error"]) for i in range(6)},
        "meta": {i: s.frames_meta(i) for i in s.complete_frames()},
        "images": {i: s.read_frame(i, images) for i in s.complete_frames()},
        "version": int(s.schema_version), "layout": s.layout.to_dict()}
pickle.dump(read, open(dump, "wb"))
'''


def _old_code(version: int, dest: Path) -> Path:
    """The stores package (and its synthetic frames) of the commit that last wrote ``version``."""
    commit = WRITERS[version]
    have = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--verify", "--quiet", commit + "^{commit}"],
                          capture_output=True, text=True)
    assert have.returncode == 0, (f"the repository's history must hold {commit} (the code that wrote schema "
                                  f"v{version}): run the tests in a full clone, not a shallow one")
    tar = subprocess.run(["git", "-C", str(ROOT), "archive", "--format=tar", commit, "stores",
                          "tests/test_stores_synthetic.py"], capture_output=True, check=True).stdout
    code = dest / f"v{version}-code"
    with tarfile.open(fileobj=io.BytesIO(tar)) as t:
        t.extractall(code, filter="data")
    return code


@pytest.fixture(scope="module", params=[1, 2], ids=["v1", "v2"])
def old_store(request, tmp_path_factory):
    """``(store, what the old code's reader read from it)`` of a store written by the old code."""
    version = request.param
    tmp = tmp_path_factory.mktemp(f"old-v{version}")
    code = _old_code(version, tmp)
    script = tmp / "write_old.py"
    script.write_text(WRITE)
    store, dump = tmp / "old.zarr", tmp / "read.pkl"
    env = {**os.environ, "PYTHONPATH": str(code)}
    r = subprocess.run([sys.executable, str(script), str(code), str(store), str(dump)], cwd=tmp, env=env,
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    read = pickle.loads(dump.read_bytes())
    assert read["version"] == version and read["complete"] == [0, 1, 2, 3, 4] and read["incomplete"] == [5]
    return store, read


def _copy(store: Path, tmp_path: Path, name: str = "s.zarr") -> Path:
    out = tmp_path / name
    shutil.copytree(store, out)
    return out


def _same_as_old_reader(path: Path, read: dict) -> None:
    """The upgraded store reads, through today's reader, exactly what the old code read from the original."""
    s = open_store(path)
    assert s.schema_version == SCHEMA_VERSION and s.layout.num_frames == FRAMES
    assert {k: v for k, v in s.layout.to_dict().items() if k != "encoding"} == \
        {k: v for k, v in read["layout"].items() if k != "encoding"}
    assert s.complete_frames() == read["complete"] and s.incomplete_frames() == read["incomplete"]
    assert s.frames_meta(5)["error"] == read["errors"][5] and "out of memory" in read["errors"][5]
    for i in read["complete"]:
        got = s.read_frame(i, list(read["images"][i]))
        for key, want in read["images"][i].items():
            assert got[key].shape == want.shape and got[key].dtype == want.dtype, key
            np.testing.assert_array_equal(got[key], want, err_msg=f"frame {i} {key}")
        meta, old = s.frames_meta(i), read["meta"][i]
        for key, value in old.items():
            if key in ("camera_to_world", "world_to_clip"):
                np.testing.assert_array_equal(meta[key], value)
            else:
                assert meta[key] == value, (i, key)
        for key in set(FRAME_META) - set(old):          # keys newer than the old store: their fill values
            assert meta[key] == ARRAY_BY_PATH[meta_path(key)].fill, key


def test_an_old_store_is_refused_with_a_line_naming_upgrade(old_store, tmp_path):
    store, read = old_store
    v = read["version"]
    with pytest.raises(SchemaVersionError, match=rf"schema v{v} store.*python -m stores upgrade"):
        open_store(store)
    from stores.schema import StoreLayout
    from stores.writer import open_or_create
    with pytest.raises(SchemaVersionError, match="python -m stores upgrade"):
        open_or_create(store, StoreLayout(**{**read["layout"], "num_frames": 8}))
    r = subprocess.run([sys.executable, "-m", "stores", "validate", str(store)], cwd=ROOT, capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 2 and r.stdout == ""
    assert r.stderr.strip().count("\n") == 0 and f"python -m stores upgrade {store}" in r.stderr


def test_upgrade_in_place_reads_what_the_old_code_read(old_store, tmp_path):
    store, read = old_store
    path = _copy(store, tmp_path)
    r = subprocess.run([sys.executable, "-m", "stores", "upgrade", str(path)], cwd=ROOT, capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert f"upgraded from schema v{read['version']} to v3: 6 frames, 5 complete, 1 incomplete" in r.stdout
    _same_as_old_reader(path, read)
    assert sorted(os.listdir(tmp_path)) == ["s.zarr"]          # nothing left beside it
    # each clip's SceneSpec JSON is kept once, at its first frame
    s = open_store(path)
    assert s.scene_json(2) == read["meta"][2]["scene_json"] and s.scene_json(4) == read["meta"][4]["scene_json"]
    r = subprocess.run([sys.executable, "-m", "stores", "upgrade", str(path)], cwd=ROOT, capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0 and "already schema v3; nothing to do" in r.stdout


def test_upgrade_to_a_new_path_leaves_the_old_store_alone(old_store, tmp_path):
    store, read = old_store
    src = _copy(store, tmp_path, "old.zarr")
    before = sorted((p.relative_to(src), p.read_bytes()) for p in src.rglob("*") if p.is_file())
    s = upgrade.upgrade(src, tmp_path / "new.zarr")
    assert s["upgraded"] and s["copied"] == 5 and s["incomplete"] == 1 and not s["damaged"]
    _same_as_old_reader(tmp_path / "new.zarr", read)
    assert sorted((p.relative_to(src), p.read_bytes()) for p in src.rglob("*") if p.is_file()) == before


def test_an_upgrade_stopped_in_its_copy_or_its_swap_is_finished_by_running_it_again(old_store, tmp_path,
                                                                                     monkeypatch):
    store, read = old_store
    path = _copy(store, tmp_path)
    from stores.writer import StoreWriter
    real, calls = StoreWriter.commit, []

    def stop_after_two(self, records, failures=None):
        if len(calls) == 2:
            raise KeyboardInterrupt
        calls.append(1)
        return real(self, records, failures)
    monkeypatch.setattr(upgrade, "BATCH", 2)
    monkeypatch.setattr(StoreWriter, "commit", stop_after_two)
    with pytest.raises(KeyboardInterrupt):
        upgrade.upgrade(path)
    monkeypatch.setattr(StoreWriter, "commit", real)
    with pytest.raises(SchemaVersionError):          # still the old store, untouched, beside a partial copy
        open_store(path)
    assert open_store(str(path) + upgrade.UPGRADING).complete_frames() == [0, 1, 2, 3]    # two commits
    s = upgrade.upgrade(path)                         # resumes: the frames copied stay
    assert s["kept"] == 4 and s["copied"] == 1
    _same_as_old_reader(path, read)
    # a swap cut short after the old store was moved aside: the next run puts the new one in place
    path2 = _copy(store, tmp_path, "t.zarr")
    upgrade.copy(path2, str(path2) + upgrade.UPGRADING)
    os.rename(path2, str(path2) + upgrade.OLD.format(read["version"]))
    s = upgrade.upgrade(path2)
    assert s["resumed_swap"]
    _same_as_old_reader(path2, read)
    assert sorted(os.listdir(tmp_path)) == ["s.zarr", "t.zarr"]


def test_a_damaged_chunk_of_an_old_store_leaves_its_frame_for_the_resume(old_store, tmp_path):
    store, read = old_store
    path = _copy(store, tmp_path)
    spec = ARRAY_BY_SOURCE["guides_normal"]
    shard = path.joinpath(*spec.path.split("/"), "c", "3", "0", "0", "0")
    data = shard.read_bytes()
    shard.write_bytes(data[: len(data) // 2])       # cut short: its shard index is gone
    r = subprocess.run([sys.executable, "-m", "stores", "upgrade", str(path)], cwd=ROOT, capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 1, r.stderr
    assert "frame 3: damaged in the old store (guides/normal" in r.stderr and "1 damaged" in r.stdout
    s = open_store(path)
    assert s.complete_frames() == [0, 1, 2, 4] and f"damaged in the schema v{read['version']} store" in s.frames_meta(3)["error"]
    assert s.scene_json(4) == read["meta"][4]["scene_json"]       # its clip's JSON came from frame 4
