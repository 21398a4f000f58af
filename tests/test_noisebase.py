"""Noisebase both ways: ``python -m pipeline export --format noisebase`` writes sequences that Noisebase's own
``TrainingSampleLoader_v1`` reads (in its own environment, zarr 2), with exact world-space positions
(re-traced samples) that reproduce our stored motion and depth; :class:`stores.noisebase.NoisebaseStore`
reads them back (zarr 3) within the RGBE encoding's error, and our per-sample kinds train on them, a
model that needs features Noisebase lacks being refused by name."""
from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from stores.contract import FEATURE_GROUPS as G, FEATURE_NAMES

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.xdist_group("noisebase")       # one worker renders the module's store once
RES = 16
CLIPS = 2                 # clips of FRAMES frames: a moving ball under a moving camera, one with defocus
FRAMES = 3
SPP = 4
# Noisebase's loader environment: its pinned zarr 2 beside this interpreter's torch and numpy
NB_PACKAGES = ("noisebase==1.1.1", "zarr==2.18.7", "numcodecs==0.15.1", "antlr4-python3-runtime==4.9.3",
               "hydra-core", "omegaconf", "asciitree", "fasteners", "deprecated", "wrapt")


def render_cfg():
    from pipeline.render import RenderConfig
    return RenderConfig(res=(RES, RES), spp=SPP, layer_levels=1, ref_spp=32, ref_passes=2, ref_min_passes=2,
                        time_slices=2)


def clip_spec(seed: int, defocus: bool):
    from test_render import ball_scene
    spec = ball_scene(motion=True, defocus=defocus, frames=FRAMES, seed=seed, cam_step=(0.2, 0.05, -0.1))
    return dataclasses.replace(spec, kind="indoor" if defocus else "outdoor")


def write_store(path, specs_frames, cfg=None) -> str:
    """A store of real renders: ``specs_frames`` = [(spec, frames to render)], the render settings recorded
    as a dataset run records them (``config['render']``)."""
    from pipeline.render import render_frame
    from stores.schema import StoreLayout
    from stores.writer import open_or_create
    cfg = cfg or render_cfg()
    n = sum(len(fr) for _, fr in specs_frames)
    layout = StoreLayout(num_frames=n, height=RES, width=RES, spp=cfg.spp, layer_spp=(1,), tile=16)
    w = open_or_create(str(path), layout, {"render": {**dataclasses.asdict(cfg), "res": list(cfg.res)}})
    i = 0
    for spec, frames in specs_frames:
        for f in frames:
            w.write_frame(i, render_frame(spec, f, cfg))
            i += 1
    return str(path)


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    specs = [(clip_spec(11 + k, defocus=k == 1), range(FRAMES)) for k in range(CLIPS)]
    return write_store(tmp_path_factory.mktemp("nb") / "clips.zarr", specs)


@pytest.fixture(scope="module")
def exported(store, tmp_path_factory):
    from pipeline.__main__ import main
    out = tmp_path_factory.mktemp("nbout") / "nb"
    assert main(["export", store, "--format", "noisebase", "--out", str(out)]) == 0
    return out


@pytest.fixture(scope="module")
def noisebase_env():
    """A folder of Noisebase 1.1.1 and its zarr 2 (pip --target, cached), put before this interpreter's
    packages; skipped with the reason where pip cannot install them (no package index)."""
    cache = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "denoise-datagen" / "noisebase-1.1.1"
    if not (cache / "noisebase").is_dir():
        tmp = cache.with_name(f"{cache.name}.{os.getpid()}.tmp")        # moved into place whole
        r = subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--target", str(tmp),
                            *NB_PACKAGES], capture_output=True, text=True, timeout=600)
        if r.returncode != 0:
            pytest.skip(f"cannot install Noisebase's loader environment ({' '.join(NB_PACKAGES)}): "
                        f"{r.stderr.strip().splitlines()[-1] if r.stderr.strip() else r.returncode}")
        try:
            os.replace(tmp, cache)
        except OSError:                 # another process put it there first
            import shutil
            shutil.rmtree(tmp, ignore_errors=True)
    return cache


def test_noisebase_loader_reads_the_export(store, exported, noisebase_env, tmp_path):
    from stores.reader import open_store
    npz = tmp_path / "read.npz"
    env = {**os.environ, "PYTHONPATH": str(noisebase_env)}
    r = subprocess.run([sys.executable, str(ROOT / "tests" / "noisebase_loader.py"), str(exported), str(npz)],
                       capture_output=True, text=True, env=env, cwd=tmp_path, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    assert f"read {CLIPS * FRAMES} frames" in r.stdout
    got = np.load(npz)
    st = open_store(store)
    seqs = json.loads((exported / "sequences.json").read_text())["sequences"]
    assert [s["frames"] for s in seqs] == [list(range(k * FRAMES, (k + 1) * FRAMES)) for k in range(CLIPS)]
    moving = 0
    for s in seqs:
        name = s["file"].removesuffix(".zip")
        for f, i in enumerate(s["frames"]):
            fr = st.read_frame(i, ["radiance", "features", "reference"])
            nbf = lambda k: got[f"{name}/{f}/{k}"]                                   # noqa: E731
            rad = np.moveaxis(fr["radiance"], -1, 0)                                   # 3 H W S
            # RGBE: less than one colour step, at most (1 + 1/256 of the log range) of the brightest channel / 255
            err = np.abs(nbf("color") - rad) / np.maximum(rad.max(axis=0, keepdims=True), 1e-30)
            assert err.max() < 1.1 / 255
            np.testing.assert_array_equal(nbf("reference"), np.moveaxis(fr["reference"], -1, 0))
            feat = fr["features"]
            np.testing.assert_array_equal(nbf("w_normal"), np.moveaxis(feat[..., G["normal"]], -1, 0))
            np.testing.assert_array_equal(nbf("diffuse"), np.moveaxis(feat[..., G["albedo"]], -1, 0))
            depth = feat[..., FEATURE_NAMES.index("depth")]
            hit = depth > 0
            # Noisebase's log depth of our positions: the distance from the camera centre (our depth is from
            # the lens point: within the aperture radius 0.25 of the defocused clip)
            dist = 1.0 / np.expm1(nbf("depth")[0].astype(np.float64))
            tol = 2.0 ** -8 * depth + (0.26 if s["clip_id"] == seqs[1]["clip_id"] else 1e-4)
            assert np.all(np.abs(dist - depth)[hit] <= tol[hit])
            if f > 0:
                # its screen motion (row, col) from our positions, world motion and cameras is our stored motion
                ours = np.moveaxis(feat[..., G["motion"]], -1, 0)[::-1]
                d = np.abs(nbf("motion") - ours)[:, hit]
                assert d.max() < 2.0 ** -8 * max(1.0, np.abs(ours).max()) + 1e-3, d.max()
                moving += int((np.abs(ours[:, hit]) > 0.5).sum())
    assert moving > 50                    # the motion compared is not all zero


def test_positions_are_the_samples_own(store):
    """The re-traced geometry is exactly the stored samples': depth bit for bit before rounding, and the
    stored motion is the projection of position + motion with the previous camera."""
    from scene_gen import projection as C
    from pipeline.render import FrameScene, render_inputs, sample_geometry
    spec = clip_spec(11, defocus=False)
    fs = FrameScene(spec, 2, render_cfg())
    _, feat, _ = render_inputs(fs)
    geo = sample_geometry(fs)
    np.testing.assert_array_equal(geo["depth"], feat[..., FEATURE_NAMES.index("depth")])
    hit = geo["depth"] > 0
    assert hit.sum() > 100 and (np.abs(geo["motion"][hit]).sum(-1) > 0).sum() > 10
    cur = C.project_pixels(fs.world_to_clip, geo["position"][hit], (RES, RES))
    prev = C.project_pixels(fs.prev_world_to_clip, (geo["position"] + geo["motion"])[hit], (RES, RES))
    np.testing.assert_allclose(prev - cur, feat[..., G["motion"]][hit], atol=1e-3)
    np.testing.assert_allclose(np.linalg.norm(geo["position"][hit] - fs.camera_to_world[:3, 3], axis=-1),
                               geo["depth"][hit], rtol=1e-5)


def test_reader_round_trip(store, exported):
    from stores.noisebase import MISSING_FEATURES, NoisebaseStore
    from stores.reader import open_store
    st, nb = open_store(store), NoisebaseStore(exported)
    assert (nb.layout.height, nb.layout.width, nb.layout.spp, nb.num_frames) == (RES, RES, SPP, CLIPS * FRAMES)
    assert list(nb.clips(None).values()) == [list(range(k * FRAMES, (k + 1) * FRAMES)) for k in range(CLIPS)]
    assert set(MISSING_FEATURES) == {"specular", "roughness", "coc", "lens", "time"}
    crop = (3, 2, 9, 11)
    for i in range(nb.num_frames):
        rad = st.read_array("inputs/radiance", i, crop, samples=3)
        got = nb.read_array("inputs/radiance", i, crop, samples=3)
        assert got.shape == rad.shape == (3, 3, 9, 11)
        assert np.all(np.abs(got - rad) <= 1.1 / 255 * rad.max(axis=1, keepdims=True) + 1e-30)
        feat, nbf = st.read_array("inputs/features", i, crop).astype(np.float32), nb.read_array("inputs/features", i, crop)
        assert nbf.shape == feat.shape and nbf.dtype == np.float32
        for g in ("normal", "albedo"):
            np.testing.assert_array_equal(nbf[:, G[g]], feat[:, G[g]])
        hit = feat[:, G["depth"]] > 0
        np.testing.assert_allclose(nbf[:, G["depth"]][hit], feat[:, G["depth"]][hit], rtol=2.0 ** -8, atol=0.26)
        if st.meta_column("frame")[i] > 0:
            np.testing.assert_allclose(nbf[:, G["motion"]], feat[:, G["motion"]], atol=0.02)
        else:
            assert not nbf[:, G["motion"]].any()              # the first frame of a sequence: no motion
        for g in MISSING_FEATURES:
            assert not nbf[:, G[g]].any()
        np.testing.assert_array_equal(nb.read_array("reference/radiance", i, crop),
                                      st.read_array("reference/radiance", i, crop))
        np.testing.assert_allclose(nb.read_array("guides/albedo", i), feat_mean(st, i, "albedo"), atol=1e-3)


def test_one_opener_reads_either_format(store, exported):
    """stores.protocol.open_training_store is every consumer's opener: a Zarr store or a Noisebase folder
    by what the path holds, a store passed through; a dataset built on a path takes the same way."""
    from stores.noisebase import NoisebaseStore
    from stores.protocol import open_training_store
    from stores.reader import Store
    from training.datasets import StoreDataset
    nb, st = open_training_store(exported), open_training_store(store)
    assert isinstance(nb, NoisebaseStore) and isinstance(st, Store) and open_training_store(nb) is nb
    ds = StoreDataset(str(exported), None, 8, False, 0)
    assert isinstance(ds.store, NoisebaseStore) and ds.store.num_frames == nb.num_frames
    from training.data import open_store
    from training.errors import DataError
    with pytest.raises(DataError, match=r"cannot open store .*nothing-here"):      # training words the error
        open_store(str(exported) + "-nothing-here")


def feat_mean(st, i, group):
    return st.read_array("inputs/features", i)[:, G[group]].astype(np.float32).mean(axis=0)


def test_export_refuses_what_noisebase_cannot_hold(store, tmp_path):
    from pipeline.export import export
    from stores.errors import ExportError
    with pytest.raises(ExportError, match="whole clip"):
        export(store, "0-1", "noisebase", str(tmp_path / "a"))
    stills = write_store(tmp_path / "stills.zarr", [(clip_spec(5, False), [0]), (clip_spec(6, False), [0])])
    with pytest.raises(ExportError, match="stills"):
        export(stills, "all", "noisebase", str(tmp_path / "b"))
    mixed = write_store(tmp_path / "mixed.zarr", [(clip_spec(5, False), range(2)), (clip_spec(6, False), range(3))])
    with pytest.raises(ExportError, match="different lengths"):
        export(mixed, "all", "noisebase", str(tmp_path / "c"))
    assert not any((tmp_path / d).exists() for d in "abc")      # a refused export leaves no folder behind


def test_export_refuses_samples_it_cannot_retrace(store, tmp_path):
    """A store whose recorded render settings are not those its samples were drawn with (another seed
    offset: other film positions) is refused before anything is written."""
    import zarr
    from pipeline.export import export
    from stores.errors import ExportError
    import shutil
    bad = tmp_path / "bad.zarr"
    shutil.copytree(store, bad)
    root = zarr.open_group(str(bad), mode="r+")
    cfg = dict(root.attrs["config"])
    cfg["render"] = {**cfg["render"], "seed_offset": 99}
    root.attrs["config"] = cfg
    with pytest.raises(ExportError, match="cannot be re-traced"):
        export(str(bad), "all", "noisebase", str(tmp_path / "out" / "nb"))
    assert not (tmp_path / "out").exists()


def cli(*args) -> int:
    from training.__main__ import main
    return main([str(a) for a in args])


def test_our_kinds_train_on_noisebase_data(exported, tmp_path, capsys):
    from kind_models import PROBES, register_probes, unregister_probes
    common = ["--steps", "2", "--batch", "2", "--crop", "8", "--spp", "4", "--workers", "0", "--device", "cpu",
              "--no-progress", "--val-split", "train", "--val-every", "2", "--val-frames", "2"]
    # the layer family reads every feature group: refused by name, then trained on the ones Noisebase has
    tiny = {"embed": 8, "context": 8, "kernel_size": 5, "unet_encoder": [[8], [8], [8]], "unet_bottleneck": [8],
            "unet_decoder": [[8], [8], [8]], "partition_hidden": [8], "kernel_hidden": [8]}
    assert cli("train", "--model", "layer", "--store", exported, "--out", tmp_path / "r0", *common,
               "--model-cfg", json.dumps(tiny)) == 2
    err = capsys.readouterr().err
    assert "['specular', 'roughness', 'coc', 'lens', 'time']" in err and '"features"' in err
    held = {**tiny, "features": ["normal", "depth", "albedo", "motion"]}
    assert cli("train", "--model", "layer", "--store", exported, "--out", tmp_path / "r1", *common,
               "--model-cfg", json.dumps(held)) == 0
    assert cli("evaluate", "--checkpoint", tmp_path / "r1" / "checkpoint.pt", "--store", exported, "--split", "train",
               "--out", tmp_path / "e.json") == 0
    res = json.loads((tmp_path / "e.json").read_text())
    assert np.isfinite(res["mean"]["psnr"]) and "ci95" in res
    # the report reads the folder through the same door: the run, the input and OIDN, its tables and figures
    assert cli("report", "--runs", tmp_path / "r1", "--store", exported, "--split", "train", "--out",
               tmp_path / "rep", "--no-flip") == 0
    md = (tmp_path / "rep" / "report.md").read_text()
    assert "r1" in md and "input" in md and (tmp_path / "rep" / "speed_vs_error.png").exists()
    # a clips model (windows of per-sample frames, stepped through them) trains on the sequences too
    register_probes()
    try:
        assert cli("train", "--model", PROBES["clips"], "--store", exported, "--out", tmp_path / "r2", *common,
                   "--model-cfg", json.dumps({"features": held["features"]})) == 0
    finally:
        unregister_probes()


def test_nppd_trains_and_is_evaluated_on_a_noisebase_folder(exported, tmp_path):
    """nppd (recurrent, per-sample, reading normal, depth and albedo: all in Noisebase) trains on the
    sequences and is evaluated and applied there clip by clip: stepping through single frames keeps the
    model's feature groups (evaluate and denoise once rebuilt its input as one of all 17 features, which
    the folder was then refused for)."""
    from training.models import get
    run = tmp_path / "run"
    assert cli("train", "--model", "nppd", "--store", exported, "--out", run, "--steps", "2", "--batch", "2",
               "--crop", "8", "--spp", "2", "--workers", "0", "--device", "cpu", "--no-progress", "--val-split",
               "train", "--val-every", "2", "--val-frames", "1", "--model-cfg", json.dumps(get("nppd").tiny)) == 0
    assert cli("evaluate", "--checkpoint", run / "checkpoint.pt", "--store", exported, "--split", "train",
               "--no-flip", "--out", tmp_path / "e.json") == 0
    res = json.loads((tmp_path / "e.json").read_text())
    assert res["method"] == "nppd" and res["clips"] >= 1 and np.isfinite(res["mean"]["psnr"])
    assert cli("denoise", "--checkpoint", run / "checkpoint.pt", "--store", exported, "--frame", FRAMES - 1,
               "--out", tmp_path / "d.exr") == 0 and (tmp_path / "d.exr").exists()


def test_unread_features_never_reach_the_network():
    import torch
    from training.models import build
    m = build("layer", embed=8, context=8, kernel_size=5, unet_encoder=((8,), (8,), (8,)), unet_bottleneck=(8,),
              unet_decoder=((8,), (8,), (8,)), features=["normal", "depth", "albedo"]).eval()
    assert m.input_spec().features == ("normal", "depth", "albedo") and m.config["features"] == ["normal", "depth", "albedo"]
    g = torch.Generator().manual_seed(0)
    rad, feat = torch.rand(1, 4, 3, 8, 8, generator=g), torch.rand(1, 4, 17, 8, 8, generator=g)
    other = feat.clone()
    for k in ("specular", "roughness", "motion", "coc", "lens", "time"):
        other[:, :, G[k]] = torch.rand_like(other[:, :, G[k]]) * 9
    with torch.no_grad():
        torch.testing.assert_close(m.denoise(rad, feat), m.denoise(rad, other))
        assert not torch.allclose(m.denoise(rad, feat), m.denoise(rad, feat * 1.5))
    from training.errors import ConfigError
    with pytest.raises(ConfigError, match="unknown feature groups"):
        build("layer", features=["normals"])


def _rewrite_zip(src: Path, dst: Path, edit) -> None:
    """``src`` copied to ``dst`` with every member passed through ``edit(name, bytes) -> bytes | None``
    (None leaves the member out)."""
    import zipfile
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w", zipfile.ZIP_STORED) as zout:
        for info in zin.infolist():
            data = edit(info.filename, zin.read(info.filename))
            if data is not None:
                zout.writestr(info, data)


@pytest.mark.parametrize("member,how", [("color/1.0.0.0.0", "lost"), ("diffuse/1.0.0.0.0", "lost"),
                                        ("reference/2.0.0.0", "lost"), ("camera_position/0.0", "lost"),
                                        ("color/1.0.0.0.0", "garbage")])
def test_a_lost_or_corrupt_chunk_is_named_never_zeros(exported, tmp_path, member, how, capsys):
    """A chunk missing from a sequence's zip (which zarr would read as its fill value, zeros) or present
    but garbage is refused by name: sequence, array, chunk; the training command exits 3 (damaged)."""
    import shutil
    from stores.errors import CorruptChunkError, MissingShardError
    from stores.noisebase import NoisebaseStore
    folder = tmp_path / "nb"
    shutil.copytree(exported, folder)
    seq = sorted(folder.glob("*.zip"))[0]
    assert member in __import__("zipfile").ZipFile(seq).namelist()
    _rewrite_zip(Path(exported) / seq.name, seq,
                 lambda name, data: data if name != member else (None if how == "lost" else b"\x07" * len(data)))
    nb = NoisebaseStore(folder)
    frame = 0 if member.startswith("camera") else int(member.split("/")[1].split(".")[0])
    err = MissingShardError if how == "lost" else CorruptChunkError
    with pytest.raises(err) as e:
        nb.read_array("inputs/radiance" if member.startswith("color") else
                      "reference/radiance" if member.startswith("reference") else "inputs/features", frame)
    assert seq.name in str(e.value) and member in str(e.value) and e.value.frame == frame
    other = sorted(folder.glob("*.zip"))[1]          # the other sequence reads as before
    assert np.isfinite(nb.read_array("inputs/radiance", FRAMES + frame)).all()
    if member == "color/1.0.0.0.0" and how == "lost":
        assert other.exists() and cli("train", "--model", "nbg", "--store", folder, "--out", tmp_path / "r",
                                      "--steps", "1", "--batch", "1", "--crop", "8", "--workers", "0",
                                      "--device", "cpu", "--no-progress") == 3
        assert member in capsys.readouterr().err


from store_contract import StoreContract, check_dtypes  # noqa: E402


class TestZarrStoreContract(StoreContract):
    """Our Zarr store of the module's clips (real renders): the training store contract."""

    @pytest.fixture
    def contract_store(self, store):
        from stores.reader import open_store
        return open_store(store)


def test_the_contract_refuses_a_dtype_the_protocol_does_not_allow(store):
    """Both ways: our store passes the dtype check; the same store returning its radiance as float16 (or
    its features as float64), where the protocol promises float32 (float16 or float32), fails it."""
    from stores.reader import open_store
    st = open_store(store)
    check_dtypes(st)

    class Narrowed:
        def __init__(self, inner, path, dtype):
            self.inner, self.path_, self.dtype = inner, path, dtype

        def __getattr__(self, name):
            return getattr(self.inner, name)

        def read_array(self, path, i, *a, **k):
            out = self.inner.read_array(path, i, *a, **k)
            return out.astype(self.dtype) if path == self.path_ else out
    for path, dtype in (("inputs/radiance", np.float16), ("inputs/features", np.float64)):
        with pytest.raises(AssertionError, match=path):
            check_dtypes(Narrowed(st, path, dtype))


class TestNoisebaseStoreContract(StoreContract):
    """The same clips exported as Noisebase sequences, read back: the same contract."""

    @pytest.fixture
    def contract_store(self, exported):
        from stores.noisebase import NoisebaseStore
        return NoisebaseStore(exported)


def test_export_splits_or_drops_a_clip_at_a_flagged_frame(store, tmp_path):
    """The middle frame of clip 0 marked incomplete (validate flags it), then `python -m pipeline export --format
    noisebase --skip-bad-frames`: the parts of the clip around it (one frame each) are no sequence, so clip 0 is
    left out with one plain line naming it, and clip 1 is exported whole (before: the whole export refused,
    pointing at --frames all, which did not help; the skip notice a raw UserWarning with its file and line).
    Parts long enough are sequences of their own: with a first and a last frame flagged, each clip's other two
    frames. Never joined across the frame: without --skip-bad-frames, --frames 0,2 is refused naming the gap."""
    import shutil

    from pipeline.__main__ import main
    from stores.noisebase import NoisebaseStore
    from stores.reader import open_store
    from stores.writer import StoreWriter
    ours = open_store(store)
    c0, c1 = (int(ours.meta_column("clip_id")[i]) for i in (0, FRAMES))
    copy = tmp_path / "gap.zarr"
    shutil.copytree(store, copy)
    StoreWriter(str(copy)).mark_failed(1, "a frame lost in the test")
    out = tmp_path / "nb"
    r = subprocess.run([sys.executable, "-m", "pipeline", "export", str(copy), "--format", "noisebase",
                        "--skip-bad-frames", "--out", str(out)], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 2 and all(x.startswith("warning: ") for x in lines), r.stderr
    assert "skipping 1 flagged frames" in lines[0] and "frame 1: incomplete" in lines[0], lines
    assert f"clip {c0} left out at its flagged frame 1" in lines[1] and "UserWarning" not in r.stderr, lines
    rows = json.loads((out / "sequences.json").read_text())["sequences"]
    assert [(x["clip_id"], x["frames"]) for x in rows] == [(c1, [3, 4, 5])]
    assert NoisebaseStore(out).num_frames == FRAMES
    # the clip alone: nothing is left to write, one line naming it, exit 2
    with pytest.warns(UserWarning, match="skipping 1 flagged frames"):
        assert main(["export", str(copy), "--format", "noisebase", "--skip-bad-frames", "--frames", "0-2",
                     "--out", str(tmp_path / "none")]) == 2
    # without --skip-bad-frames the gap is refused, never joined
    assert main(["export", str(copy), "--format", "noisebase", "--frames", "0,2", "--out", str(tmp_path / "g")]) == 2
    # a first and a last frame flagged: clips 0 and 1 each split into their other two frames, two sequences of 2
    both = tmp_path / "ends.zarr"
    shutil.copytree(store, both)
    for i in (0, 2 * FRAMES - 1):
        StoreWriter(str(both)).mark_failed(i, "a frame lost in the test")
    with pytest.warns(UserWarning) as rec:
        assert main(["export", str(both), "--format", "noisebase", "--skip-bad-frames", "--out",
                     str(tmp_path / "ends")]) == 0
    said = [str(w.message) for w in rec]
    assert len(said) == 2 and said[0].startswith("skipping 2 flagged frames"), said
    assert f"clip {c0} split at its flagged frame 0 into frames 1-2; clip {c1} split at its flagged frame 5 into " \
           "frames 3-4" in said[1], said
    rows = json.loads((tmp_path / "ends" / "sequences.json").read_text())["sequences"]
    assert [(x["clip_id"], x["frames"]) for x in rows] == [(c0, [1, 2]), (c1, [3, 4])]
    nb = NoisebaseStore(tmp_path / "ends")
    assert nb.frames_per_sequence == [2, 2]
    for k, i in enumerate([1, 2, 3, 4]):          # each sequence frame is its store frame (within RGBE's error)
        np.testing.assert_allclose(nb.read_array("reference/radiance", k), ours.read_array("reference/radiance", i),
                                   rtol=1e-6)


def test_a_folder_keeps_the_splits_it_declares(store, exported, tmp_path, capsys):
    """An exported folder reads each sequence in the split of the clip it came from (sequences.json), so a
    store's test clip stays test data: train on a folder of test sequences finds no training frame,
    evaluate --split test reads them all. Without sequences.json (Noisebase's own data) the splits are
    ours; a run records which; a sequences.json without every sequence's split is one line, exit 2."""
    import shutil

    from stores.noisebase import NoisebaseStore
    from stores.reader import open_store
    from training.models import get
    ours = open_store(store)
    folder = NoisebaseStore(exported)
    assert folder.split_source == "declared (sequences.json)"
    rows = json.loads((exported / "sequences.json").read_text())["sequences"]
    for n, row in enumerate(rows):
        assert folder.split_of_frame(int(folder.offsets[n])) == ours.split_of_frame(row["frames"][0]) == row["split"]
    test_only = tmp_path / "test-only"
    shutil.copytree(exported, test_only)
    doc = json.loads((test_only / "sequences.json").read_text())
    for row in doc["sequences"]:
        row["split"] = "test"                           # as an export of a store's test clips writes it
    (test_only / "sequences.json").write_text(json.dumps(doc))
    nb = NoisebaseStore(test_only)
    assert nb.frames_in_split("train") == [] and nb.frames_in_split("test") == list(range(nb.num_frames))
    common = ["--steps", "1", "--batch", "1", "--crop", "8", "--spp", "2", "--workers", "0", "--device", "cpu",
              "--no-progress", "--model-cfg", json.dumps(get("nppd").tiny)]
    assert cli("train", "--model", "nppd", "--store", test_only, "--out", tmp_path / "r", *common) == 2
    assert "train" in capsys.readouterr().err
    assert cli("evaluate", "--checkpoint", "input", "--store", test_only, "--split", "test", "--no-flip",
               "--out", tmp_path / "e.json") == 0
    assert len(json.loads((tmp_path / "e.json").read_text())["frames"]) == nb.num_frames
    undeclared = tmp_path / "undeclared"
    shutil.copytree(exported, undeclared)
    (undeclared / "sequences.json").unlink()
    assert NoisebaseStore(undeclared).split_source.startswith("ours")
    assert cli("train", "--model", "nppd", "--store", undeclared, "--out", tmp_path / "r2", "--val-split", "train",
               *common) == 0
    import torch
    ck = torch.load(tmp_path / "r2" / "checkpoint.pt", weights_only=False)
    assert ck["store"]["split_source"].startswith("ours")
    doc["sequences"][0].pop("split")
    (test_only / "sequences.json").write_text(json.dumps(doc))
    assert cli("evaluate", "--checkpoint", "input", "--store", test_only, "--out", tmp_path / "e2.json") == 2
    err = capsys.readouterr().err
    assert "declares no split for 1 of the" in err, err


def test_hard_cases_runs_on_a_noisebase_folder(exported, tmp_path):
    """`python -m training hard-cases --store NOISEBASE_FOLDER` (the input and OIDN, no runs): exit 0 and a
    table of its frames, where it died with a KeyError on the renderer-NaN columns the format lacks."""
    r = subprocess.run([sys.executable, "-m", "training", "hard-cases", "--store", str(exported), "--out",
                        str(tmp_path / "hc")], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0 and "Traceback" not in r.stderr, r.stdout[-2000:] + r.stderr[-3000:]
    res = json.loads((tmp_path / "hc" / "hard-cases.json").read_text())
    assert set(res["frames"]) == {"input", "oidn"} and all(
        len(rows) == CLIPS * FRAMES for rows in res["frames"].values())


def test_both_export_commands_offer_every_format(store, exported, tmp_path, capsys):
    """`python -m stores export` and `python -m pipeline export` take the same formats, the noisebase
    plug-in included (it had only the store's own), and write the same Noisebase sequences."""
    from pipeline.__main__ import main as pipeline_main
    from pipeline.export import FORMATS
    from stores.__main__ import main as stores_main
    from stores.export import writers
    assert set(FORMATS) == set(writers()) >= {"exr", "oidn", "layerdenoise", "noisebase"}
    out = tmp_path / "via-stores"
    assert stores_main(["export", store, "--format", "noisebase", "--out", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == sorted(p.name for p in exported.iterdir())
    import zipfile
    for p in exported.glob("*.zip"):             # the same members, byte for byte (a zip also records times)
        with zipfile.ZipFile(p) as a, zipfile.ZipFile(out / p.name) as b:
            assert sorted(a.namelist()) == sorted(b.namelist()), p.name
            assert all(a.read(m) == b.read(m) for m in a.namelist()), p.name
    for main in (stores_main, pipeline_main):
        with pytest.raises(SystemExit):
            main(["export", "--help"])
        assert "noisebase" in capsys.readouterr().out


@pytest.mark.parametrize("damage", ["truncated", "no normal"])
def test_a_damaged_sequence_file_exits_3(exported, tmp_path, damage, capsys):
    """A sequence zip cut short (zipfile: "File is not a zip file") or without its ``normal`` array is damage,
    as the README says of Noisebase folders: `train` and `evaluate` exit 3 with one line naming the file and
    what is wrong (before: exit 2, as for bad settings)."""
    import shutil
    folder = tmp_path / "nb"
    shutil.copytree(exported, folder)
    rows = json.loads((folder / "sequences.json").read_text())["sequences"]
    seq = folder / next(r["file"] for r in rows if r["split"] == "train")      # one the commands below read
    if damage == "truncated":
        data = seq.read_bytes()
        seq.write_bytes(data[:len(data) // 2])
    else:
        _rewrite_zip(Path(exported) / seq.name, seq, lambda name, data: None if name.startswith("normal/") else data)
    capsys.readouterr()
    assert cli("evaluate", "--checkpoint", "input", "--store", folder, "--split", "train", "--no-flip",
               "--out", tmp_path / "e.json") == 3
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and seq.name in err, err
    assert ("truncated" in err) if damage == "truncated" else ("'normal'" in err), err
    assert cli("train", "--model", "nbg", "--store", folder, "--out", tmp_path / "r", "--steps", "1", "--batch", "1",
               "--crop", "8", "--workers", "0", "--device", "cpu", "--no-progress", "--val-split", "train") == 3
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and seq.name in err, err
