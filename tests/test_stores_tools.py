"""Validator (with a writer killed mid-frame by SIGKILL), exports (exr, oidn, layerdenoise), CLI, bench."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from stores import bench, codecs, export, validate
from stores.__main__ import main as stores_main
from stores.errors import ExportError
from stores.reader import open_store
from stores.schema import StoreLayout
from stores.writer import StoreWriter, open_or_create
from test_stores_synthetic import stored, synthetic_frame

ROOT = Path(__file__).resolve().parents[1]
H, W, S = 12, 16, 4


@pytest.fixture()
def store2(tmp_path):
    path = tmp_path / "s.zarr"
    w = open_or_create(path, StoreLayout(num_frames=2, height=H, width=W, spp=S, tile=8))
    frames = [synthetic_frame(20 + i, H, W, S, motion=True, defocus=True) for i in range(2)]
    for i, fr in enumerate(frames):
        w.write_frame(i, fr)
    return path, frames


def _write_frames(path, frames, tile=8):
    w = open_or_create(path, StoreLayout(num_frames=len(frames), height=H, width=W, spp=S, tile=tile))
    for i, fr in enumerate(frames):
        w.write_frame(i, fr)
    return path


CHILD = textwrap.dedent("""
    import sys, time
    sys.path[:0] = [{root!r}, {tests!r}]
    from stores.writer import StoreWriter
    from test_stores_synthetic import synthetic_frame
    def progress(name):
        if name == "inputs/features":       # radiance and features of the new frame are on disk
            print("MID", flush=True)
            time.sleep(120)
    StoreWriter({path!r}).write_frame(1, synthetic_frame(77, {h}, {w}, {s}), on_progress=progress)
    print("DONE", flush=True)
""")


def test_writer_killed_mid_frame_is_flagged_and_rerun_completes(store2, tmp_path, capsys):
    path, frames = store2
    assert stores_main(["validate", str(path)]) == 0
    capsys.readouterr()
    script = tmp_path / "child.py"
    script.write_text(CHILD.format(root=str(ROOT), tests=str(ROOT / "tests"), path=str(path), h=H, w=W, s=S))
    proc = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "MID"
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.wait(timeout=60)
    assert proc.returncode == -signal.SIGKILL
    # the frame was complete before; the killed re-run left it incomplete, not half-valid
    rep = validate.validate_store(path)
    assert rep.incomplete == [1] and not rep.ok
    assert stores_main(["validate", str(path)]) == 1
    assert "incomplete: [1]" in capsys.readouterr().out
    assert StoreWriter(path).incomplete_frames() == [1]
    # half-written new radiance is on disk, but readers refuse the frame
    with pytest.raises(Exception, match="incomplete"):
        open_store(path).read_frame(1)
    # the re-run (what the Dask stage does for incomplete_frames()) completes it
    for i in StoreWriter(path).incomplete_frames():
        StoreWriter(path).write_frame(i, synthetic_frame(77, H, W, S))
    assert stores_main(["validate", str(path)]) == 0
    np.testing.assert_array_equal(open_store(path).read_frame(1)["radiance"],
                                  stored("radiance", synthetic_frame(77, H, W, S)["radiance"], open_store(path).layout))


def test_validator_finds_bad_values(store2):
    path, _ = store2
    fr = synthetic_frame(5, H, W, S)
    fr["radiance"][0, 0, 0, 0] = np.nan
    fr["radiance"][1, 1, 0, 0] = np.inf
    fr["features"][2, 2, :, 4] = 1.7               # albedo_r > 1
    fr["reference"][3, 3, 1] = -0.5
    StoreWriter(path).write_frame(0, fr)
    rep = validate.validate_store(path)
    f0, f1 = rep.frames
    assert f0.nonfinite["radiance"] == 2
    text = " | ".join(f0.problems)
    assert "radiance: 2 NaN/Inf" in text and "features.albedo has" in text and "values above 1 (max 1.7" in text \
        and "reference has 1 negative values" in text
    assert not f1.problems and f1.ref_rel_stderr == pytest.approx(0.01, rel=0.2)
    assert f0.ranges["reference"][0] == -0.5
    assert stores_main(["validate", str(path), "--frames", "1"]) == 0
    assert stores_main(["validate", str(path), "--json"]) == 1


def test_validate_cli_exit_codes(tmp_path, store2):
    path, _ = store2
    run = lambda *a: subprocess.run([sys.executable, "-m", "stores", *a], cwd=ROOT,  # noqa: E731
                                    capture_output=True, text=True, timeout=120)
    ok = run("validate", str(path), "-v")
    assert ok.returncode == 0, ok.stderr
    assert "OK" in ok.stdout and "frame      1" in ok.stdout
    missing = run("validate", str(tmp_path / "missing.zarr"))
    assert missing.returncode == 2 and "no store" in missing.stderr


def test_export_exr(store2, tmp_path):
    path, frames = store2
    assert stores_main(["export", str(path), "--frames", "1", "--format", "exr", "--out", str(tmp_path / "e")]) == 0
    d = tmp_path / "e" / "frame_000001"
    lay = open_store(path).layout
    fr = {k: stored(k, v, lay) for k, v in frames[1].items() if k != "meta"}   # what the store holds
    mean = export.read_exr(str(d / "input_mean.exr"))["RGB"]
    np.testing.assert_allclose(mean, fr["radiance"].mean(axis=2), rtol=1e-6)
    np.testing.assert_array_equal(export.read_exr(str(d / "layer_0004spp.exr"))["RGB"], fr["layers"][2])
    np.testing.assert_array_equal(export.read_exr(str(d / "reference.exr"))["RGB"], frames[1]["reference"])
    np.testing.assert_array_equal(export.read_exr(str(d / "depth.exr"))["Z"], fr["guides_depth"][..., 0])
    mo = export.read_exr(str(d / "motion.exr"))
    assert sorted(mo) == ["motion_to_prev.x", "motion_to_prev.y"]          # names that say what they are
    np.testing.assert_array_equal(mo["motion_to_prev.x"], fr["guides_motion"][..., 0])
    np.testing.assert_array_equal(mo["motion_to_prev.y"], fr["guides_motion"][..., 1])
    from PIL import Image
    png = Image.open(d / "reference.png")
    assert png.size == (W, H) and png.mode == "RGB"
    from core.images import to_srgb8            # the training tone map (values: tests/test_tonemap_io.py)
    np.testing.assert_array_equal(np.asarray(png), to_srgb8(frames[1]["reference"]))
    assert not (tmp_path / "e" / "frame_000000").exists()
    assert sorted(os.listdir(tmp_path / "e")) == ["frame_000001"]          # no temporary folder left


def test_export_oidn_naming(store2, tmp_path):
    path, frames = store2
    export.export(path, "0-1", "oidn", str(tmp_path / "o"))
    names = sorted(os.listdir(tmp_path / "o"))
    assert "f000000_0001spp.hdr.exr" in names and "f000001_0032spp.nrm.exr" in names
    assert "f000001_ref.hdr.exr" in names and "f000001_ref.alb.exr" in names
    # OIDN's grouping rule (training/dataset.py): group = name before the last '_' when the suffix is
    # NNNNspp or ref; inputs are the sorted names but the last, the target is the last.
    groups = {}
    for n in names:
        stem = n.rsplit(".", 2)[0]
        prefix, suffix = stem.rsplit("_", 1)
        assert suffix == "ref" or (suffix.endswith("spp") and suffix[:-3].isdecimal())
        groups.setdefault(prefix, set()).add(stem)
    assert set(groups) == {"f000000", "f000001"}
    members = sorted(groups["f000001"])
    assert members[-1] == "f000001_ref" and len(members) == 7
    ref = export.read_exr(str(tmp_path / "o" / "f000001_ref.hdr.exr"))["RGB"]
    np.testing.assert_array_equal(ref, frames[1]["reference"])
    l8 = export.read_exr(str(tmp_path / "o" / "f000001_0008spp.hdr.exr"))["RGB"]
    np.testing.assert_array_equal(l8, stored("layers", frames[1]["layers"], open_store(path).layout)[3])


def test_export_layerdenoise_matches_its_loader(store2, tmp_path):
    h5py = pytest.importorskip("h5py")
    path, frames = store2
    inp, ref = export.export(path, "all", "layerdenoise", str(tmp_path / "l"), name="synthetic_set")
    scene = os.path.basename(inp)
    # layerdenoise train.py: ref file = scene[0:scene.rfind("_")] + "_ref.h5"
    assert os.path.basename(ref) == scene[0:scene.rfind("_")] + "_ref.h5"
    with h5py.File(inp, "r") as f, h5py.File(ref, "r") as r:
        chans = {"color": 3, "normals_depth": 4, "albedo": 3, "specular": 4, "uvt": 3, "motionvecs": 3}
        for k, c in chans.items():
            assert f[k].shape == (2, S, c, H, W) and f[k].dtype == np.float16, k
        assert r["color"].shape == (2, 3, H, W) and r["color"].dtype == np.float16
        # the loader's slicing: [idx, 0:spp, ..., oh:oh+ch, ow:ow+cw]
        color = f["color"][1, 0:2, ..., 2:10, 3:11]
        target = r["color"][1, ..., 2:10, 3:11]
        assert color.shape == (2, 3, 8, 8) and target.shape == (3, 8, 8)
        fr = dict(frames[1])
        # the features as the store keeps them (compact2: each group to its own mantissa bits)
        fr["features"] = stored("features", fr["features"], open_store(path).layout)
        expect = np.minimum(fr["radiance"][2:10, 3:11, 0:2], 65504).transpose(2, 3, 0, 1)
        np.testing.assert_allclose(color.astype(np.float32), expect, rtol=1e-3)
        np.testing.assert_allclose(target.astype(np.float32), np.minimum(fr["reference"], 65504)[2:10, 3:11].transpose(2, 0, 1), rtol=1e-3)
        mv = f["motionvecs"][1].astype(np.float32)                       # (S, 3, H, W)
        np.testing.assert_allclose(mv[:, 0], fr["features"][..., 11].transpose(2, 0, 1) * 2 / W, rtol=1e-3, atol=1e-4)
        np.testing.assert_allclose(mv[:, 1], -fr["features"][..., 12].transpose(2, 0, 1) * 2 / H, rtol=1e-3, atol=1e-4)
        nd = f["normals_depth"][1].astype(np.float32)
        R = fr["camera_to_world"][:3, :3]
        n_world = fr["features"][..., 0:3]
        n_cam = np.einsum("ij,hwsj->hwsi", np.linalg.inv(R), n_world)   # Mitsuba camera frame (+x left)
        n_view = n_cam * np.array([-1.0, 1.0, -1.0])                      # layerdenoise: +x right, +z to viewer
        np.testing.assert_allclose(nd[:, 0:3], n_view.transpose(2, 3, 0, 1), atol=2e-3)
        assert nd[:, 3].max() == pytest.approx(1.0, abs=1e-3) and nd[:, 3].min() >= 0
        spec = f["specular"][1].astype(np.float32)
        np.testing.assert_allclose(spec[:, 3], fr["features"][..., 10].transpose(2, 0, 1), atol=1e-3)
        uvt = f["uvt"][1].astype(np.float32)
        np.testing.assert_allclose(uvt[:, 2], fr["features"][..., 16].transpose(2, 0, 1), atol=1e-3)


def test_export_layerdenoise_view_normals_and_per_clip_depth(tmp_path):
    """Normals in layerdenoise's view space (+x right, +y up, +z towards the viewer), as its
    augment_rot90 / flips assume; depth divided by one scale per clip, not per frame."""
    h5py = pytest.importorskip("h5py")
    path = tmp_path / "c.zarr"
    w = open_or_create(path, StoreLayout(num_frames=4, height=H, width=W, spp=S, tile=8))
    frames = [synthetic_frame(5, H, W, S, frame=k, num_frames=3, motion=True) for k in range(3)]
    frames.append(synthetic_frame(6, H, W, S))
    frames[2]["features"][..., 3] *= 3.0                    # the clip's deepest frame
    c2w = frames[0]["camera_to_world"][:3, :3]
    right, up, to_viewer = -c2w[:, 0], c2w[:, 1], -c2w[:, 2]  # Mitsuba camera: +x left, +z forward
    f = frames[0]["features"]
    f[0, 0, :, 0:3], f[0, 1, :, 0:3], f[0, 2, :, 0:3] = right, up, to_viewer
    for i, fr in enumerate(frames):
        w.write_frame(i, fr)
    inp, _ = export.export(path, [0, 1, 3], "layerdenoise", str(tmp_path / "l"))   # frame 2 not exported
    lay = open_store(path).layout
    for fr in frames:                                         # the features as the store keeps them
        fr["features"] = stored("features", fr["features"], lay)
    with h5py.File(inp, "r") as h:
        nd = h["normals_depth"][...].astype(np.float32)     # (F, S, 4, H, W)
        tol = 2e-3 + 2.0 ** -(codecs.FEATURE_KEEPBITS["normal"] + 1)     # float16 + the store's rounding
        np.testing.assert_allclose(nd[0, :, 0:3, 0, 0], np.tile([1, 0, 0], (S, 1)), atol=tol)
        np.testing.assert_allclose(nd[0, :, 0:3, 0, 1], np.tile([0, 1, 0], (S, 1)), atol=tol)
        np.testing.assert_allclose(nd[0, :, 0:3, 0, 2], np.tile([0, 0, 1], (S, 1)), atol=tol)
        scales = h.attrs["depth_scale"]
        clip_max = max(float(fr["features"][..., 3].max()) for fr in frames[:3])
        np.testing.assert_allclose(scales, [clip_max, clip_max, frames[3]["features"][..., 3].max()], rtol=1e-3)
        for j, i in enumerate([0, 1]):                       # the same depth, the same value in every frame
            np.testing.assert_allclose(nd[j, :, 3], frames[i]["features"][..., 3].transpose(2, 0, 1) / clip_max,
                                       rtol=2e-3, atol=1e-4)
        assert nd[1, :, 3].max() < 0.5                        # frame 1 is not stretched to 1 on its own


def test_export_errors(store2, tmp_path):
    from stores.errors import UnfitFrameError
    path, _ = store2
    StoreWriter(path).mark_failed(0, "boom")
    with pytest.raises(UnfitFrameError, match=r"frame 0: incomplete \(last error: boom\)"):
        export.export(path, "all", "oidn", str(tmp_path / "x"))
    with pytest.raises(ExportError, match="unknown export format"):
        export.export(path, "1", "png", str(tmp_path / "x"))
    assert stores_main(["export", str(path), "--frames", "5", "--format", "exr", "--out", str(tmp_path / "x")]) == 2


def test_bench_smoke():
    r = bench.run(crops=3, crop=32, frames=1, size=32, verbose=False)
    for k in ("crops_per_s", "mb_per_s", "ceiling_mb_per_s", "fraction_of_ceiling", "stored_over_raw"):
        assert r[k] > 0, k
    assert r["stored_over_raw"] < 1.0
    chosen = [row for row in r["codecs"] if "chosen" in row["encoding"]][0]
    lz4 = [row for row in r["codecs"] if "the lz4 encoding" in row["encoding"]][0]
    f16 = [row for row in r["codecs"] if row["encoding"].startswith("float16")][0]
    assert chosen["inf_after_encoding"] == 0 and f16["inf_after_encoding"] > 0   # sun disc overflows float16
    assert chosen["ratio"] < 0.8 * lz4["ratio"]
    assert r["encoding"] == codecs.DEFAULT_ENCODING == "compact3" and "crops/s" in bench.format_report(r)


def test_bench_reencode_smoke(tmp_path):
    """``python -m stores bench --reencode``: per-group ratios of every encoding, the lossy ones' errors
    (measured from a lossless lz4 store: re-encoding a compact store is exact, its values have 9 bits)."""
    path = tmp_path / "l.zarr"
    w = open_or_create(path, StoreLayout(num_frames=2, height=H, width=W, spp=S, tile=8, encoding="lz4"))
    for i in range(2):
        w.write_frame(i, synthetic_frame(20 + i, H, W, S, motion=True, defocus=True))
    r = bench.reencode([str(path)], frames=2, crops=2, verbose=False)
    row = r["stores"][str(path)]
    assert r["encodings"] == ["compact3", "compact", "lz4"]
    for enc in ("compact3", "compact"):
        assert set(row[enc]["ratio"]) == {"inputs/radiance", "inputs/features", "layers", "reference", "guides"}
        assert r["all"][enc]["total"] < 0.8 * r["all"]["lz4"]["total"]
        assert r["all"][enc]["ratio"]["inputs/radiance"] < 0.8 * r["all"]["lz4"]["ratio"]["inputs/radiance"]
        assert 2 ** -12 < r["errors"][enc]["radiance"]["max"] <= 2 ** -10
        assert row[enc]["write_ms_per_frame"] > 0
    assert r["all"]["compact3"]["ratio"]["inputs/features"] < r["all"]["compact"]["ratio"]["inputs/features"]
    assert r["radiance_rel_error"] == r["errors"]["compact3"]["radiance"]
    lens = 2.0 ** -(codecs.FEATURE_KEEPBITS["lens"] + 1)              # compact3 rounds the lens coarser
    assert r["errors"]["compact"]["features/lens"] <= 2 ** -10 < r["errors"]["compact3"]["features/lens"] <= lens
    assert row["zeros_changed"] == 0 and row["reference_bit_exact"]
    assert "of the ceiling" in bench.format_reencode(r)


def test_pipeline_cli_dispatches_to_stores(store2, tmp_path, capsys):
    """``python -m pipeline validate|export`` use stores.validate/export ``add_arguments`` + ``run``."""
    pm = pytest.importorskip("pipeline.__main__")
    path, _ = store2
    assert pm.main(["validate", str(path)]) == 0
    assert pm.main(["export", str(path), "--format", "oidn", "--frames", "0", "--out", str(tmp_path / "o")]) == 0
    assert (tmp_path / "o" / "f000000_ref.hdr.exr").exists()
    assert pm.main(["validate", str(tmp_path / "missing.zarr")]) == 2
    assert "no store" in capsys.readouterr().err


def test_reference_limits_match_a_simulated_reference():
    """The PSNR ceiling and relMSE floor are what the true image scores against a noisy reference."""
    from core.images import tonemap
    from stores import fitness
    rng = np.random.default_rng(3)
    truth = rng.uniform(0.05, 4.0, (64, 64, 3))
    se = 0.02 * truth + 0.002
    ref = truth + rng.normal(size=truth.shape) * se
    psnr, floor = fitness.reference_limits(ref, se)
    mse = np.mean((tonemap(truth) - tonemap(ref)) ** 2)
    assert psnr == pytest.approx(10 * np.log10(1 / mse), abs=0.3)
    assert floor == pytest.approx(np.mean((truth - ref) ** 2 / (ref ** 2 + 0.01)), rel=0.1)
    assert fitness.reference_limits(ref, np.zeros_like(se)) == (float("inf"), 0.0)
    # halving the error raises the ceiling by 20 log10(2) dB
    assert fitness.reference_limits(ref, se / 2)[0] - psnr == pytest.approx(6.02, abs=0.05)


def test_validate_states_the_reference_error(tmp_path, store2):
    path, _ = store2
    rep = validate.validate_store(path)
    done = [f for f in rep.frames if f.complete]
    assert done and all(f.psnr_ceiling is not None and f.psnr_ceiling > 10 for f in done)
    text = rep.format()
    assert "PSNR ceiling" in text and "relMSE floor" in text and "10/50/90 %" in text


@pytest.mark.parametrize("fmt", ["exr", "oidn", "layerdenoise"])
@pytest.mark.parametrize("spoil", ["nan", "negative", "zero"])
def test_export_refuses_frames_validate_flags(tmp_path, capsys, fmt, spoil):
    """A NaN, negative or all-zero reference (written through zarr-python, past the writer's checks) is
    refused by every export format, naming the frame, and nothing is written; --skip-bad-frames leaves it
    out and names it."""
    import zarr
    path = tmp_path / "s.zarr"
    frames = [synthetic_frame(i, H, W, S) for i in range(3)]
    _write_frames(path, frames)
    ref = zarr.open_array(str(path / "reference" / "radiance"), mode="r+").with_config({"write_empty_chunks": True})
    if spoil == "nan":
        ref[1, 0, 2, 3] = np.nan
    elif spoil == "negative":
        ref[1, 1, 2, 3] = -4.0
    else:
        ref[1] = 0.0
    out = tmp_path / "out"
    args = [str(path), "--format", fmt, "--out", str(out)]
    assert stores_main(["export", *args]) == 2
    err = capsys.readouterr().err
    want = {"nan": "reference: 1 NaN/Inf values", "negative": "reference has 1 negative values",
            "zero": "reference is all zero while the input radiance is not"}[spoil]
    assert "frame 1:" in err and want in err and "--skip-bad-frames" in err, err
    assert not out.exists() or not os.listdir(out)
    with pytest.warns(UserWarning, match=r"skipping 1 flagged frames .*frame 1:"):
        assert stores_main(["export", *args, "--skip-bad-frames"]) == 0
    names = " ".join(sorted(os.listdir(out)))
    assert "000001" not in names and "000000" in names or fmt == "layerdenoise"
    if fmt == "layerdenoise":
        import h5py
        with h5py.File(out / "dataset_input.h5") as f:
            assert list(f.attrs["frames"]) == [0, 2]


def test_an_export_that_stops_leaves_nothing_behind(tmp_path, capsys):
    """A damaged shard of the last frame stops the export (exit 3): no half-written frame folders stay
    in --out, and what was there before is untouched."""
    path = tmp_path / "s.zarr"
    _write_frames(path, [synthetic_frame(i, H, W, S) for i in range(3)])
    out = tmp_path / "out"
    out.mkdir()
    (out / "mine.txt").write_text("keep me")
    f = path / "layers" / "radiance" / "c" / "2" / "0" / "0" / "0" / "0"
    f.write_bytes(f.read_bytes()[:-40])
    assert stores_main(["export", str(path), "--format", "exr", "--out", str(out)]) == 3
    assert sorted(os.listdir(out)) == ["mine.txt"] and (out / "mine.txt").read_text() == "keep me"
