"""Fault injection on real stores on disk: every way a store's files can be damaged, and what the
validator (``python -m pipeline validate``: exit code and message), the readers (fast shard path and
zarr fallback), the datasets and the resume path make of it. No mocks: files are deleted, truncated,
overwritten and edited in place."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from pipeline.__main__ import main as pipeline_main
from stores import chunk_files, schema
from stores.errors import (ArrayMetadataError, CorruptChunkError, MissingShardError, StoreCorruptionError,
                           StoreLayoutError)
from stores.reader import frame_problems, open_store
from stores.schema import StoreLayout
from core.cli import DAMAGED as EXIT_DAMAGED, OK as EXIT_OK, PROBLEMS as EXIT_PROBLEMS
from stores.validate import validate_store
from stores.writer import StoreWriter, frames_with_missing_data, open_or_create
from test_stores_synthetic import synthetic_frame

H = W = 16
S = 2
LAYOUT = StoreLayout(num_frames=3, height=H, width=W, spp=S, tile=8)     # 2x2 inner chunks per shard


def _write(path, layout=LAYOUT, frames=None):
    w = open_or_create(path, layout, {})
    frames = frames or [synthetic_frame(i, H, W, S, motion=False) for i in range(layout.num_frames)]
    for i, fr in enumerate(frames):
        w.write_frame(i, fr)
    return frames


@pytest.fixture()
def store(tmp_path):
    path = tmp_path / "s.zarr"
    _write(path)
    return path


def _shard(path, array, frame):
    """The file holding ``array``'s chunk or shard of ``frame`` in the store at ``path``."""
    spec = schema.ARRAY_BY_PATH[array]
    return os.path.join(path, *array.split("/"), *chunk_files.chunk_key(spec, frame).split("/"))


def _validate(path, capsys):
    code = pipeline_main(["validate", str(path)])
    out = capsys.readouterr()
    return code, out.out + out.err


def test_clean_store_validates(store, capsys):
    code, text = _validate(store, capsys)
    assert code == EXIT_OK and text.strip().endswith("OK"), text


def test_v2_writes_every_chunk_even_all_zero(store):
    """Static frames have all-zero motion: zarr would skip that shard; v2 writes it."""
    assert not open_store(store).read_array("guides/motion", 0).any()
    for spec in schema.ARRAYS:
        if spec.per_frame:
            for i in range(3):
                assert chunk_files.chunk_file(open_store(store).root, spec, i)[0], (spec.path, i)


# ----------------------------------------------------------------------------- 2. missing shards
def test_missing_shard_is_named_by_validate_readers_dataset_and_resume(store, capsys):
    lost = [("guides/motion", 1), ("reference/radiance", 1), ("inputs/radiance", 2)]
    for a, i in lost:
        os.remove(_shard(store, a, i))
    code, text = _validate(store, capsys)
    assert code == EXIT_DAMAGED and "STORE DAMAGED" in text, text
    for a, i in lost:                                   # every missing shard, with its array and frame
        assert f"{a}: frame {i} is complete but its chunk file {_shard(store, a, i)} is missing" in text, text
    for fast in (True, False):                          # fast path and zarr fallback
        st = open_store(store, fast=fast)
        with pytest.raises(MissingShardError, match=r"guides/motion: frame 1 .*c/1/0/0/0 is missing") as e:
            st.read_array("guides/motion", 1)
        assert (e.value.array, e.value.frame, e.value.path) == ("guides/motion", 1, _shard(store, "guides/motion", 1))
        with pytest.raises(MissingShardError, match="inputs/radiance: frame 2"):
            st.read_frame(2)
        st.read_frame(0)                                # the intact frame still reads
    torch = pytest.importorskip("torch")  # noqa: F841
    from training.datasets import SampleFrames
    ds = SampleFrames(store, split=None, spp=S, crop=8, augment=False)
    with pytest.raises(MissingShardError):
        ds[[w[-1] for w in ds.windows].index(2)]
    # resume: the writer side counts them as incomplete, so `pipeline dataset` re-renders them
    w = StoreWriter(store)
    assert w.incomplete_frames() == [1, 2] and not w.frame_complete(1) and w.frame_complete(0)
    assert sorted(frames_with_missing_data(store)) == [1, 2]
    for i in w.incomplete_frames():
        w.write_frame(i, synthetic_frame(i, H, W, S, motion=False))
    assert w.incomplete_frames() == [] and _validate(store, capsys)[0] == EXIT_OK


def test_incomplete_frame_without_shards_is_not_damage(tmp_path, capsys):
    path = tmp_path / "s.zarr"
    w = open_or_create(path, LAYOUT, {})
    w.write_frame(0, synthetic_frame(0, H, W, S))
    code, text = _validate(path, capsys)
    assert code == EXIT_PROBLEMS and "incomplete" in text and "DAMAGE" not in text, text
    assert open_store(path).read_frame(1, ["reference"], allow_incomplete=True)["reference"].max() == 0


# ----------------------------------------------------------------------------- 4. truncated / garbage
@pytest.mark.parametrize("how", ["truncate", "garbage", "empty", "index"])
def test_damaged_shard_raises_corrupt_chunk_error(store, capsys, how):
    f = _shard(store, "inputs/features", 1)
    data = open(f, "rb").read()
    if how == "truncate":
        data = data[: len(data) // 2]
    elif how == "garbage":
        data = np.random.default_rng(0).integers(0, 256, len(data), dtype=np.uint8).tobytes()
    elif how == "empty":
        data = b""
    else:                                       # a shard index pointing past the end of the file, crc fixed up
        from stores.codecs import crc32c
        n = 4 * 16
        idx = np.frombuffer(data[-n - 4:-4], "<u8").copy()
        idx[0] = len(data) * 10
        body = idx.tobytes()
        data = data[:-n - 4] + body + crc32c(body).to_bytes(4, "little")
    with open(f, "wb") as fh:
        fh.write(data)
    code, text = _validate(store, capsys)
    assert code == EXIT_DAMAGED and "inputs/features: frame 1" in text and f in text, text
    assert "Traceback" not in text
    for fast in (True, False):
        with pytest.raises(CorruptChunkError, match="inputs/features: frame 1") as e:
            open_store(store, fast=fast).read_frame(1, ["features"])
        assert e.value.frame == 1 and e.value.array == "inputs/features"
    if how == "index":
        with pytest.raises(CorruptChunkError, match="outside"):
            open_store(store).read_array("inputs/features", 1)


# ----------------------------------------------------------------------------- 5. checksums
@pytest.mark.parametrize("array", ["inputs/radiance", "reference/radiance", "guides/depth"])
def test_one_flipped_byte_inside_a_chunk_is_detected(store, capsys, array):
    f = _shard(store, array, 2)
    data = bytearray(open(f, "rb").read())
    data[20] ^= 0x01                            # inside the first inner chunk (not the index)
    open(f, "wb").write(bytes(data))
    code, text = _validate(store, capsys)
    assert code == EXIT_DAMAGED and f"{array}: frame 2" in text and "crc32c" in text, text
    for fast in (True, False):
        with pytest.raises(CorruptChunkError, match=f"{array}: frame 2"):
            open_store(store, fast=fast).read_array(array, 2)


def test_mark_damaged_lets_a_resume_rerender_corrupt_frames(store, capsys):
    f = _shard(store, "layers/radiance", 2)
    data = bytearray(open(f, "rb").read())
    data[30] ^= 0x80
    open(f, "wb").write(bytes(data))
    assert StoreWriter(store).incomplete_frames() == []      # a flipped byte is not visible to the resume...
    assert pipeline_main(["validate", str(store), "--mark-damaged"]) == EXIT_DAMAGED
    assert "marked 1 damaged frame(s) incomplete: [2]" in capsys.readouterr().err
    w = StoreWriter(store)
    assert w.incomplete_frames() == [2] and w.errors()[2].startswith("damaged: layers/radiance: frame 2")
    w.write_frame(2, synthetic_frame(2, H, W, S, motion=False))    # ...until validate marks it
    assert _validate(store, capsys)[0] == EXIT_OK


def test_mark_damaged_refuses_while_a_dataset_run_holds_the_store(store, capsys):
    from stores.lock import StoreLock
    from test_pipeline_safety import read_lock
    f = _shard(store, "layers/radiance", 1)
    data = bytearray(open(f, "rb").read())
    data[30] ^= 0x80
    open(f, "wb").write(bytes(data))
    before = open(_shard(store, "status/complete", 1), "rb").read()
    with StoreLock(store, command="dataset run"):
        code = pipeline_main(["validate", str(store), "--mark-damaged"])
        err = capsys.readouterr().err
        assert code == 2 and "not marking the damaged frames [1]" in err and "in use by another dataset run" in err, err
        assert "(dataset run)" in err
    assert open(_shard(store, "status/complete", 1), "rb").read() == before and StoreWriter(store).incomplete_frames() == []
    assert pipeline_main(["validate", str(store), "--mark-damaged"]) == EXIT_DAMAGED   # free again: marked
    assert StoreWriter(store).incomplete_frames() == [1] and read_lock(store) is None
    capsys.readouterr()


# ----------------------------------------------------------------------------- 3. edited metadata
@pytest.mark.parametrize("edit,expect", [
    (lambda m: m.update(data_type="int32"), "data_type 'int32', the schema says 'float32'"),
    (lambda m: m.update(shape=[3, 3, 16, 8]), "shape (3, 3, 16, 8), the layout says (3, 3, 16, 16)"),
    (lambda m: m["codecs"][0]["configuration"]["codecs"].pop(), "codecs"),
    (lambda m: m.update(dimension_names=["frame", "c", "y", "x"]), "dimension names"),
])
def test_edited_zarr_json_is_refused(store, capsys, edit, expect):
    f = os.path.join(store, "reference", "radiance", "zarr.json")
    meta = json.load(open(f))
    edit(meta)
    json.dump(meta, open(f, "w"))
    code, text = _validate(store, capsys)
    assert code == EXIT_DAMAGED and "reference/radiance" in text and expect in text, text
    with pytest.raises(ArrayMetadataError, match="reference/radiance") as e:
        open_store(store)
    assert isinstance(e.value, StoreLayoutError) and isinstance(e.value, StoreCorruptionError)
    with pytest.raises(ArrayMetadataError):
        StoreWriter(store)
    torch = pytest.importorskip("torch")  # noqa: F841
    from training.datasets import SampleFrames
    with pytest.raises(ArrayMetadataError):
        SampleFrames(store, split=None, spp=S, crop=8)


def test_deleted_array_is_damage(store, capsys):
    import shutil
    shutil.rmtree(os.path.join(store, "guides", "motion"))
    code, text = _validate(store, capsys)
    assert code == EXIT_DAMAGED and "guides/motion: missing" in text, text
    with pytest.raises(ArrayMetadataError, match="guides/motion: missing"):
        open_store(store)


def test_validate_cli_exit_codes_in_a_subprocess(store, tmp_path):
    """The real command line: 0 ok, 2 not a store, 3 damaged (one line on stderr, no traceback)."""
    env = dict(os.environ, PYTHONPATH=os.getcwd())
    run = lambda p: subprocess.run([sys.executable, "-m", "pipeline", "validate", str(p)],  # noqa: E731
                                   capture_output=True, text=True, env=env, timeout=120)
    assert run(store).returncode == EXIT_OK
    (tmp_path / "plain").mkdir()
    r = run(tmp_path / "plain")
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    f = _shard(store, "layers/radiance", 0)
    open(f, "wb").write(open(f, "rb").read()[:-30])
    r = run(store)
    assert r.returncode == EXIT_DAMAGED and "layers/radiance: frame 0" in r.stdout and "Traceback" not in r.stderr
    help_ = subprocess.run([sys.executable, "-m", "pipeline", "validate", "--help"], capture_output=True,
                           text=True, env=env, timeout=120).stdout
    assert "3 the store is damaged" in " ".join(help_.split()) and "1 problems found" in " ".join(help_.split())


# ----------------------------------------------------------------------------- 6. suspicious frames
def test_all_zero_reference_with_nonzero_input_is_flagged(tmp_path, capsys):
    path = tmp_path / "s.zarr"
    frames = [synthetic_frame(i, H, W, S) for i in range(3)]
    frames[1]["reference"][:] = 0
    frames[2]["reference"][0, 0, 0] = -1.0
    frames[2]["meta"]["nonfinite_inputs"] = 5
    _write(path, frames=frames)
    code, text = _validate(path, capsys)
    assert code == EXIT_PROBLEMS and "reference is all zero while the input radiance is not" in text, text
    st = open_store(path)
    assert frame_problems(st, 0) == []
    assert any("all zero" in p for p in frame_problems(st, 1))
    p2 = st.frame_problems(2)
    assert any("negative" in p for p in p2) and any("5 NaN/Inf values in its input samples" in p for p in p2)


def test_a_guide_normal_longer_than_one_is_flagged(tmp_path, capsys):
    """A per-pixel normal is the mean of unit vectors, never longer than 1: (0.95, 0.95, 0.95) (length
    1.65, each component in range) is flagged; a mean that is short (0.5) or a miss (0) is not."""
    path = tmp_path / "s.zarr"
    frames = [synthetic_frame(i, H, W, S) for i in range(3)]
    frames[1]["guides_normal"][2, 3] = 0.95
    frames[2]["guides_normal"][2, 3] = [0.5, 0.0, 0.0]
    frames[2]["guides_normal"][4, 4] = 0.0
    _write(path, frames=frames)
    code, text = _validate(path, capsys)
    assert code == EXIT_PROBLEMS and "guides_normal has 1 pixels longer than 1 (max 1.65" in text, text
    st = open_store(path)
    assert frame_problems(st, 0) == [] and frame_problems(st, 2) == []


def test_black_frame_is_not_flagged(tmp_path):
    path = tmp_path / "s.zarr"
    fr = synthetic_frame(0, H, W, S)
    for k in ("radiance", "layers", "reference", "reference_stderr"):
        fr[k][:] = 0
    _write(path, StoreLayout(num_frames=1, height=H, width=W, spp=S, tile=8), frames=[fr])
    assert frame_problems(open_store(path), 0) == [] and validate_store(path).ok


# ----------------------------------------------------------------------------- xarray
def test_xarray_coordinates_and_consolidated_metadata(store):
    xr = pytest.importorskip("xarray")
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter("error")              # no "consolidated metadata" warning
        # but zarr's note that the compact chain's numcodecs.bitround is not in the v3 spec (SCHEMA.md)
        warnings.filterwarnings("ignore", message="Numcodecs codecs are not in the Zarr version 3")
        frames = xr.open_zarr(str(store), group="frames")
        layers = xr.open_zarr(str(store), group="layers")
        guides = xr.open_zarr(str(store), group="guides")
    assert list(frames["frame"].values) == [0, 1, 2] and list(frames["frame_in_clip"].values) == [0, 0, 0]
    assert frames.sel(frame=2)["scene_seed"].values == 2
    assert list(layers["spp"].values) == list(LAYOUT.layer_spp) and "spp" in layers.coords
    assert layers["radiance"].sel(level=3).shape == (3, 3, H, W)
    assert list(guides["rgb"].values) == ["r", "g", "b"] and list(guides["xyz"].values) == ["x", "y", "z"]
    assert list(guides["uv"].values) == ["u", "v"]


def test_grow_extends_frame_coordinates_and_consolidated_metadata(store):
    xr = pytest.importorskip("xarray")
    root, lay = schema.open_group(store, mode="r+")
    schema.grow(root, lay, 5)
    assert list(xr.open_zarr(str(store), group="status")["frame"].values) == [0, 1, 2, 3, 4]
    assert open_store(store).num_frames == 5 and StoreWriter(store).incomplete_frames() == [3, 4]


@pytest.mark.parametrize("damage", ["missing", "flipped", "truncated"])
def test_train_and_evaluate_refuse_a_damaged_store(tmp_path, capsys, damage):
    """The training CLI stops with exit 3 and a one-line message naming array, frame and file (no
    traceback, also when the read happens in a DataLoader worker)."""
    from test_training import make_store
    from core.cli import DAMAGED as TRAIN_DAMAGED
    from training.__main__ import main as train_main
    path = make_store(tmp_path / "t.zarr")
    st = open_store(path)
    frame = st.frames_in_split("train")[0]
    f = _shard(path, "inputs/radiance", frame)
    if damage == "missing":
        os.remove(f)
    else:
        data = bytearray(open(f, "rb").read())
        if damage == "flipped":
            data[20] ^= 0x01
        else:
            data = data[: len(data) // 2]
        open(f, "wb").write(bytes(data))
    args = ["--store", path, "--steps", "2", "--crop", "16", "--batch", "4", "--spp", "2", "--no-progress",
            "--val-every", "0", "--val-frames", "1", "--out", str(tmp_path / "run")]
    for workers in ("0", "1"):
        code = train_main(["train", "--model", "pixelgather", "--workers", workers, *args])
        err = capsys.readouterr().err
        assert code == TRAIN_DAMAGED, err
        assert "inputs/radiance" in err and f"frame {frame}" in err and "Traceback" not in err, err
    code = train_main(["evaluate", "--checkpoint", "input", "--store", path, "--split", "train", "--no-flip",
                       "--out", str(tmp_path / "e.json")])
    err = capsys.readouterr().err
    assert code == TRAIN_DAMAGED and "inputs/radiance" in err and "Traceback" not in err, err


def test_every_entry_point_exits_3_on_a_damaged_store(store, tmp_path, capsys):
    """export (both command lines) agrees with validate: 3 for damage, 2 for other bad input."""
    from stores.__main__ import main as stores_main
    f = _shard(store, "reference/radiance", 1)
    data = bytearray(open(f, "rb").read())
    data[20] ^= 0x01
    open(f, "wb").write(bytes(data))
    for main, cmd in ((pipeline_main, []), (stores_main, [])):
        code = main(["export", str(store), "--format", "exr", "--out", str(tmp_path / "x"), *cmd])
        err = capsys.readouterr().err
        assert code == EXIT_DAMAGED and "the store is damaged" in err and "reference/radiance: frame 1" in err, err
    assert pipeline_main(["export", str(tmp_path / "none.zarr"), "--format", "exr", "--out", str(tmp_path / "y")]) == 2
    assert pipeline_main(["validate", str(store)]) == EXIT_DAMAGED
    capsys.readouterr()


# ----------------------------------------------------------------------------- 2. missing metadata chunks
@pytest.mark.parametrize("fast", [True, False])
def test_missing_camera_matrix_chunk_is_not_a_zero_matrix(store, capsys, fast):
    f = _shard(store, "frames/camera_to_world", 1)
    assert f.endswith(os.path.join("c", "0", "0", "0"))       # one chunk holds every frame's matrix
    os.remove(f)
    st = open_store(store, fast=fast)
    for read in (lambda: st.frames_meta(1), lambda: st.read_frame(1), lambda: st.read_frame(1, ["camera_to_world"])):
        with pytest.raises(MissingShardError, match="frames/camera_to_world: frame 1 is marked complete") as e:
            read()
        assert (e.value.array, e.value.frame, e.value.path) == ("frames/camera_to_world", 1, f)
    assert list(st.complete_flags()) == [True] * 3 and list(st.metadata_damage()) == [0, 1, 2]
    code, text = _validate(store, capsys)
    assert code == EXIT_DAMAGED, text
    assert f"frames/camera_to_world: frame 1 is complete but its chunk file {f} is missing" in text, text
    assert text.count("frames/camera_to_world: frame 1") == 1, text


def test_missing_clip_id_chunk_is_not_clip_0(store, capsys):
    """A lost frames/clip_id chunk would read as clip 0 and could move the frame to another split."""
    f = _shard(store, "frames/clip_id", 1)
    os.remove(f)
    st = open_store(store)
    for read in (lambda: st.frames_in_split("train"), lambda: st.split_of_frame(1), lambda: st.clips(),
                 lambda: st.frames_meta(1), lambda: st.read_frame(1, ["reference"])):
        with pytest.raises(MissingShardError, match=f"frames/clip_id: frame [01] .*{f} is missing") as e:
            read()          # whole-store questions name the first frame the chunk held, frame questions frame 1
        assert (e.value.array, e.value.path) == ("frames/clip_id", f) and e.value.frame in (0, 1)
    assert list(st.metadata_damage()) == [0, 1, 2]          # the chunk held all three
    code, text = _validate(store, capsys)
    assert code == EXIT_DAMAGED and f"frames/clip_id: frame 1 is complete but its chunk file {f} is missing" in text
    torch = pytest.importorskip("torch")  # noqa: F841
    from training.datasets import SampleFrames
    with pytest.raises(MissingShardError, match="frames/clip_id: frame 0"):
        SampleFrames(store, split="train", spp=S, crop=8)


def _flip(f, at=0):
    data = bytearray(open(f, "rb").read())
    data[at] ^= 0x04
    open(f, "wb").write(bytes(data))


# ----------------------------------------------------------------------------- 4. completion flag metadata
@pytest.mark.parametrize("how", ["deleted", "garbage"])
@pytest.mark.parametrize("extra", [[], ["--frames", "0"], ["--json"]])
def test_validate_on_a_lost_completion_flag_zarr_json_exits_3(store, capsys, how, extra):
    f = os.path.join(store, "status", "complete", "zarr.json")
    if how == "deleted":
        os.remove(f)
    else:
        open(f, "w").write("{ not json")
    code = pipeline_main(["validate", str(store), *extra])
    out = capsys.readouterr()
    text = out.out + out.err
    assert code == EXIT_DAMAGED, text
    assert "status/complete: " + ("missing" if how == "deleted" else "unreadable zarr.json") in text, text


# ----------------------------------------------------------------------------- schema v3: shared metadata chunks
def test_v3_a_frame_is_its_image_shards_plus_shared_metadata(tmp_path):
    """Schema v3: a frame's own files are its nine image shards (and, at a clip's first frame, the
    clip's SceneSpec JSON); every frames/* and status/* value lives in chunks of META_CHUNK frames."""
    from test_stores_synthetic import synthetic_frame as sf
    path = tmp_path / "s.zarr"
    frames = [sf(i, H, W, S) for i in range(5)]
    for i, fr in enumerate(frames):                       # one clip of 5 frames: scene JSON once
        fr["meta"].update(frame=i, num_frames=5, clip_id=77)
    _write(path, StoreLayout(num_frames=5, height=H, width=W, spp=S, tile=8), frames=frames)
    images = [s for s in schema.ARRAYS if s.image]
    for i in range(5):
        assert all(chunk_files.chunk_file(open_store(path).root, s, i)[0] for s in images)
    json_files = list((path / "frames" / "scene_json" / "c").iterdir())
    assert [f.name for f in json_files] == ["0"]           # the clip's first frame only
    for spec in schema.ARRAYS:
        if spec.per_frame and not spec.image and not spec.clip_first:
            files = [f for f in (path / spec.path).rglob("*") if f.is_file() and f.name != "zarr.json"]
            assert len(files) == 1 and spec.chunks(StoreLayout(5, H, W))[0] == schema.META_CHUNK, spec.path
    st = open_store(path)
    assert all(st.scene_json(i) == frames[0]["meta"]["scene_json"] for i in range(5))
    assert st.frames_meta(3)["scene_json"] == frames[0]["meta"]["scene_json"]
    np.testing.assert_array_equal(st.frames_meta(4)["camera_to_world"], frames[4]["camera_to_world"])
    assert validate_store(path).ok


def test_v3_a_damaged_shared_chunk_damages_its_frames_and_a_resume_rewrites_it(store, capsys):
    """A flipped byte in the frames/clip_id chunk (every frame's): validate names it for each complete
    frame (exit 3); --mark-damaged marks them all; writing the frames again rebuilds the chunk."""
    f = _shard(store, "frames/clip_id", 1)
    _flip(f)
    code, text = _validate(store, capsys)
    assert code == EXIT_DAMAGED and all(f"frames/clip_id: frame {i}" in text for i in range(3)), text
    assert pipeline_main(["validate", str(store), "--mark-damaged"]) == EXIT_DAMAGED
    assert "marked 3 damaged frame(s) incomplete: [0, 1, 2]" in capsys.readouterr().err
    w = StoreWriter(store)
    assert w.incomplete_frames() == [0, 1, 2]
    for i in range(3):
        w.write_frame(i, synthetic_frame(i, H, W, S, motion=False))
    assert _validate(store, capsys)[0] == EXIT_OK


def test_v3_commit_rebuilds_a_damaged_chunk_without_leaving_its_other_frames_complete(store):
    """A commit that meets a damaged metadata chunk writes it again from the new values, and marks the
    chunk's other frames incomplete (their values are gone), never complete with fill values."""
    _flip(_shard(store, "frames/scene_seed", 0))
    w = StoreWriter(store)
    w.write_frame(1, synthetic_frame(1, H, W, S, motion=False))
    assert w.incomplete_frames() == [0, 2]
    assert "metadata chunk" in w.errors()[0] and open_store(store).frames_meta(1)["complete"]


def test_v3_a_lost_flag_chunk_is_damage_for_its_frames(store, capsys):
    os.unlink(_shard(store, "status/complete", 1))
    code, text = _validate(store, capsys)
    assert code == EXIT_DAMAGED and all(f"status/complete: frame {i}" in text for i in range(3)), text
    assert StoreWriter(store).incomplete_frames() == [0, 1, 2]


def test_v3_a_lost_scene_json_is_damage(store, capsys):
    f = _shard(store, "frames/scene_json", 2)
    os.unlink(f)
    code, text = _validate(store, capsys)
    assert code == EXIT_DAMAGED and "frames/scene_json: frame 2" in text and f in text, text
    with pytest.raises(MissingShardError, match="frames/scene_json: frame 2"):
        open_store(store).clips()


def test_v3_a_clip_committed_before_its_first_frame_is_incomplete_not_damaged(tmp_path, capsys):
    """A dataset run killed after a metadata commit that holds a clip's later frames but not yet its first
    (the frames' tasks end in any order; the clip's SceneSpec JSON was stored before any of them): the
    store is incomplete (exit 1, frames left, a re-run finishes them), never damaged; every complete
    frame reads its scene, and the resume completes the store."""
    from test_stores_synthetic import synthetic_frame as sf
    path = tmp_path / "s.zarr"
    frames = [sf(5, H, W, S, frame=k, num_frames=4, scene_seed=5) for k in range(4)]
    for k, fr in enumerate(frames):
        fr["meta"].update(frame=k, num_frames=4, clip_id=42)
    w = open_or_create(path, StoreLayout(num_frames=6, height=H, width=W, spp=S, tile=8), {})
    w.write_frame(0, sf(1, H, W, S))                       # a still before the clip: clip frames 2..5
    w.write_frame(1, sf(2, H, W, S))
    w.write_scene_json(2, frames[0]["meta"]["scene_json"])  # what the scene task stores first
    w.commit({i: w.write_frame_data(i, frames[i - 2]) for i in (4, 5)})
    code, text = _validate(path, capsys)
    assert code == EXIT_PROBLEMS and "DAMAGE" not in text and "--mark-damaged" not in text, text
    assert "2 of 6 frames are incomplete" in text and "python -m pipeline dataset" in text, text
    st = open_store(path)
    assert st.metadata_damage() == {} and st.complete_frames() == [0, 1, 4, 5]
    assert st.scene_json(5) == frames[0]["meta"]["scene_json"] and st.clips()[42] == [4, 5]
    w.commit({i: w.write_frame_data(i, frames[i - 2]) for i in (2, 3)})
    assert _validate(path, capsys)[0] == EXIT_OK


def test_v3_a_clips_scene_json_is_written_only_where_it_is_missing_or_damaged(tmp_path):
    """A resume stores each clip's SceneSpec JSON again (its scene task runs for the clip's incomplete
    frames): the file of a complete frame is not rewritten when it holds those bytes (on S3 each write is
    a request), and a lost or damaged one is written again."""
    from test_stores_synthetic import synthetic_frame as sf
    path = tmp_path / "s.zarr"
    frames = [sf(5, H, W, S, frame=k, num_frames=2, scene_seed=5) for k in range(2)]
    for k, fr in enumerate(frames):
        fr["meta"].update(frame=k, num_frames=2, clip_id=9)
    _write(path, StoreLayout(num_frames=2, height=H, width=W, spp=S, tile=8), frames=frames)
    f = _shard(path, "frames/scene_json", 0)
    text = frames[0]["meta"]["scene_json"]
    os.utime(f, ns=(1, 1))
    StoreWriter(path).write_scene_json(0, text)
    assert os.stat(f).st_mtime_ns == 1                       # there already: not written
    _flip(f)
    StoreWriter(path).write_scene_json(0, text)
    assert os.stat(f).st_mtime_ns != 1 and open_store(path).scene_json(1) == text
    os.unlink(f)
    StoreWriter(path).write_scene_json(0, text)
    assert validate_store(path).ok


@pytest.mark.parametrize("frame", [0, schema.META_CHUNK + 1])
def test_v3_an_interruption_inside_a_chunks_first_commit_leaves_its_frame_incomplete_not_damaged(
        tmp_path, monkeypatch, capsys, frame):
    """A commit killed after it wrote ``status/error`` and before ``status/complete`` (the last write), in
    the first commit into a chunk of META_CHUNK frames (the store's first, and one past a chunk
    boundary): validate says incomplete (exit 1), never damaged (exit 3), and a resume completes it."""
    import stores.writer as writer_mod
    path = tmp_path / "s.zarr"
    layout = StoreLayout(num_frames=schema.META_CHUNK + 3, height=H, width=W, spp=S, tile=8)
    w = open_or_create(path, layout, {})
    if frame:
        w.write_frame(0, synthetic_frame(0, H, W, S, motion=False))
    real = writer_mod._set_many

    def killed_at_the_flags(arr, values):
        if arr.path == "status/complete" and any(v is True for _, v in values):
            raise KeyboardInterrupt
        return real(arr, values)
    monkeypatch.setattr(writer_mod, "_set_many", killed_at_the_flags)
    with pytest.raises(KeyboardInterrupt):
        w.write_frame(frame, synthetic_frame(frame, H, W, S, motion=False))
    monkeypatch.setattr(writer_mod, "_set_many", real)
    code = pipeline_main(["validate", str(path), "--frames", f"{frame}"])
    out = capsys.readouterr()
    assert code == EXIT_PROBLEMS, out.out + out.err
    assert "status/complete" not in out.out + out.err and "DAMAGED" not in out.out + out.err
    assert frame in StoreWriter(path).incomplete_frames()
    StoreWriter(path).write_frame(frame, synthetic_frame(frame, H, W, S, motion=False))
    assert open_store(path).frames_meta(frame)["complete"]
