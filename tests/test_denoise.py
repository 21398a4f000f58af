"""``python -m training denoise``: EXR images, store frames and render-frame .npz files through a saved
checkpoint, checked against evaluation's own output for the same frame; clear errors; tiles."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from core.images import read_exr, write_exr
from test_temporal import make_clip_store
from test_training import make_store
from training import checkpoint as ckpt
from training.__main__ import main
from training.config import TrainConfig
from training.models import build


def save_model(path, name, store, **over):
    """A checkpoint of a freshly initialised ``name`` (tiny settings), as `train` writes it."""
    from training.data import open_store
    torch.manual_seed(0)
    m = build(name, **{**build(name).tiny, **over})
    cfg = TrainConfig(model=name, model_cfg=dict(m.config), steps=1, batch=1, crop=16, workers=0)
    ckpt.save(path, model=m, optimizer=None, step=0, cfg=cfg,
              store_info={"schema_version": open_store(store).schema_version, "path": str(store)})
    return str(path)


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    return make_store(tmp_path_factory.mktemp("dn") / "tiny.zarr", h=32, w=32, spp=2, per_split=(1, 1, 2))


@pytest.fixture(scope="module")
def clips(tmp_path_factory):
    return make_clip_store(tmp_path_factory.mktemp("dnc") / "clips.zarr", clips=(1, 1, 1), frames=3)


def _evaluated(ck, store, index, spp=None):
    """Evaluation's output for store frame ``index`` (the oracle: the path `report` takes)."""
    from training.data import open_store
    from training.evaluate import evaluate
    split = open_store(store).split_of_frame(index)
    r = evaluate(ck, store, split=split, spp=spp, with_flip=False, keep=tuple(range(64)))
    pos = [f["index"] for f in r["frames"]].index(index)
    return r["images"][pos]


def _test_frame(store):
    from training.data import open_store
    return open_store(store).frames_in_split("test")[0]


def _exr_inputs(store, index, tmp_path, spp=1):
    """The per-pixel item of ``index`` (mean of the first ``spp`` samples and of their features) as EXRs."""
    from training.data import open_store
    from training.inputs import pixel_item_from_samples
    st = open_store(store)
    rad = torch.from_numpy(np.ascontiguousarray(st.read_array("inputs/radiance", index)[:spp])).float()
    feat = torch.from_numpy(np.ascontiguousarray(st.read_array("inputs/features", index)[:spp])).float()
    item = pixel_item_from_samples(rad, feat)
    paths = {}
    for k, v in item.items():
        img = v.permute(1, 2, 0).numpy()
        paths[k] = str(write_exr(tmp_path / f"{k}.exr", img, "RGB" if img.shape[-1] == 3 else "Y"))
    return paths


def _run(*args):
    return main(["denoise", *map(str, args)])


def test_exr_images_give_evaluations_output(store, tmp_path):
    ck = save_model(tmp_path / "wskpn.pt", "wskpn", store)
    i = _test_frame(store)
    p = _exr_inputs(store, i, tmp_path)
    assert _run("--checkpoint", ck, "--input", p["radiance"], "--albedo", p["albedo"], "--normal", p["normal"],
                "--depth", p["depth"], "--out", tmp_path / "out.exr") == 0
    out, names = read_exr(tmp_path / "out.exr")
    want = _evaluated(ck, store, i)
    assert names == "RGB" and out.shape == want.shape == (32, 32, 3)
    np.testing.assert_allclose(out, want, rtol=1e-4, atol=1e-5)
    noisy, _ = read_exr(p["radiance"])
    assert np.abs(out - noisy).mean() > 1e-4                        # it did filter


def test_store_frames_for_per_sample_recurrent_and_oidn(store, clips, tmp_path):
    i = _test_frame(store)
    ck = save_model(tmp_path / "layer.pt", "layer", store)
    assert _run("--checkpoint", ck, "--store", store, "--frame", i, "--spp", 2, "--out", tmp_path / "l.exr") == 0
    np.testing.assert_allclose(read_exr(tmp_path / "l.exr")[0], _evaluated(ck, store, i, spp=2), rtol=1e-4, atol=1e-5)
    # a recurrent sampler: the last frame of a clip, after the frames before it (state carried, as evaluation)
    from training.data import open_store
    st = open_store(clips)
    last = st.clips("test")[next(iter(st.clips("test")))][-1]
    tk = save_model(tmp_path / "temporal.pt", "temporal", clips)
    assert _run("--checkpoint", tk, "--store", clips, "--frame", last, "--spp", 2, "--out", tmp_path / "t.exr") == 0
    got = read_exr(tmp_path / "t.exr")[0]
    np.testing.assert_allclose(got, _evaluated(tk, clips, last, spp=2), rtol=1e-4, atol=1e-5)
    assert _run("--checkpoint", "oidn", "--store", store, "--frame", i, "--out", tmp_path / "o.exr") == 0
    assert np.isfinite(read_exr(tmp_path / "o.exr")[0]).all()


def test_render_frame_npz(mi, tmp_path, capsys):
    """The .npz of `python -m pipeline render-frame` (a real Mitsuba render) for a per-pixel, a per-sample
    and a sampler model."""
    from pipeline.__main__ import main as pipeline_main
    npz = tmp_path / "f.npz"
    assert pipeline_main(["render-frame", "--seed", "3", "--kind", "indoor", "--res", "16", "--spp", "2",
                          "--ref-spp", "16", "--out", str(npz)]) == 0
    z = np.load(npz)
    store = make_store(tmp_path / "s.zarr", h=16, w=16, spp=2, per_split=(1, 0, 0))     # schema for the checkpoints
    for name in ("nbg", "layer", "temporal"):
        ck = save_model(tmp_path / f"{name}.pt", name, store)
        out = tmp_path / f"{name}.exr"
        assert _run("--checkpoint", ck, "--input", npz, "--spp", 2, "--out", out) == 0
        img = read_exr(out)[0]
        assert img.shape == (16, 16, 3) and np.isfinite(img).all()
    # an edited .npz with NaN samples is refused, naming the array and the count
    bad = {k: z[k] for k in z.files}
    bad["radiance"] = bad["radiance"].copy()
    bad["radiance"][2, 3, 0, :] = np.nan
    np.savez(tmp_path / "bad.npz", **bad)
    ck = str(tmp_path / "nbg.pt")
    assert _run("--checkpoint", ck, "--input", tmp_path / "bad.npz", "--spp", 2, "--out", tmp_path / "b.exr") == 2
    assert not (tmp_path / "b.exr").exists()
    assert "radiance of" in capsys.readouterr().err


def test_clear_errors(store, tmp_path, capsys):
    ck = save_model(tmp_path / "wskpn.pt", "wskpn", store)
    i = _test_frame(store)
    p = _exr_inputs(store, i, tmp_path)
    base = ["--checkpoint", ck, "--input", p["radiance"], "--out", tmp_path / "o.exr"]

    def err(*extra):
        assert _run(*base, *extra) == 2
        return capsys.readouterr().err

    assert "--depth missing" in err("--albedo", p["albedo"], "--normal", p["normal"])
    write_exr(tmp_path / "small.exr", np.ones((16, 16, 3), np.float32))
    assert "16x16" in err("--albedo", tmp_path / "small.exr", "--normal", p["normal"], "--depth", p["depth"])
    bad = read_exr(p["radiance"])[0]
    bad[3, 5] = np.nan
    bad[7, 1, 2] = np.inf
    base[3] = str(write_exr(tmp_path / "nan.exr", bad))
    e = err("--albedo", p["albedo"], "--normal", p["normal"], "--depth", p["depth"])
    assert "2 pixel(s) with NaN or Inf" in e and "y=3, x=5" in e
    lk = save_model(tmp_path / "layer.pt", "layer", store)
    assert _run("--checkpoint", lk, "--input", p["radiance"], "--out", tmp_path / "o.exr") == 2
    assert "--store S --frame I" in capsys.readouterr().err
    assert _run("--checkpoint", tmp_path / "none.pt", "--input", p["radiance"], "--out", tmp_path / "o.exr") == 2
    assert _run("--checkpoint", ck, "--store", store, "--frame", 99, "--out", tmp_path / "o.exr") == 2
    assert "frames 0..3" in capsys.readouterr().err
    assert not (tmp_path / "o.exr").exists()


def test_tiles_cover_the_image_once_and_match_the_whole_pass(store, tmp_path):
    from training.denoise import denoise, tiles
    H, W = 100, 77
    seen = np.zeros((H, W), int)
    for (y0, y1, x0, x1), (ky0, ky1, kx0, kx1) in tiles(H, W, 32):
        assert y0 % 16 == 0 and x0 % 16 == 0 and y0 <= ky0 and ky1 <= y1 and x0 <= kx0 and kx1 <= x1
        seen[ky0:ky1, kx0:kx1] += 1
    assert (seen == 1).all()
    # a 96x96 per-pixel item: 9 tiles of 32 px with 32 px of context against one pass
    g = torch.Generator().manual_seed(1)
    yy, xx = torch.meshgrid(torch.linspace(0, 6, 96), torch.linspace(0, 6, 96), indexing="ij")
    base = (torch.sin(yy) * torch.cos(xx) + 1.5).expand(3, 96, 96)
    item = {"radiance": base * (1 + 0.5 * torch.rand(3, 96, 96, generator=g)),
            "albedo": torch.full((3, 96, 96), 0.5), "normal": torch.tensor([0.0, 0.0, 1.0]).view(3, 1, 1).expand(3, 96, 96),
            "depth": torch.ones(1, 96, 96), "motion": torch.zeros(2, 96, 96)}
    for name in ("wskpn", "nbg"):        # both look no further than the margin: tiles change nothing
        m = build(name, **build(name).tiny).for_inference()
        whole = denoise(m, [item], tile=-1)
        tiled = denoise(m, [item], tile=32)
        assert np.isfinite(tiled).all() and np.abs(whole - item["radiance"].permute(1, 2, 0).numpy()).mean() > 0.05
        assert np.abs(tiled - whole).max() < 1e-5 * np.abs(whole).max(), name


def _aov_exr(mi, path, res=32):
    """Mitsuba's own multichannel EXR: the Cornell box through its ``aov`` integrator (R, G, B beside
    albedo.R/G/B, sh_normal.X/Y/Z, depth.T), written by ``mi.Bitmap.write``; and its layers as Mitsuba
    splits them (the oracle of which channel is which)."""
    scene = mi.cornell_box()
    scene["sensor"]["film"].update(width=res, height=res)
    scene["integrator"] = {"type": "aov", "aovs": "albedo:albedo,sh_normal:sh_normal,depth:depth",
                           "img": {"type": "path"}}
    sc = mi.load_dict(scene)
    mi.render(sc, spp=4)
    bmp = sc.sensors()[0].film().bitmap()
    bmp.write(str(path))
    return {name: np.array(b, copy=True).reshape(res, res, -1) for name, b in bmp.split()}


def test_channels_are_read_by_name_from_mitsubas_own_aov_file(mi, store, tmp_path, capsys):
    """One multichannel AOV file as --input, --albedo, --normal and --depth gives what separate files of
    Mitsuba's own layers give (before: every guide was the file's first channels, B, G, R); a layer's
    channels are read R, G, B / X, Y, Z, never in the file's alphabetical order; a file without the
    channels a guide needs (an albedo image as --depth) is one line naming the channels, exit 2."""
    ck = save_model(tmp_path / "wskpn.pt", "wskpn", store)
    aov = tmp_path / "aov.exr"
    layers = _aov_exr(mi, aov)
    assert {"albedo", "sh_normal", "depth"} <= set(layers)
    sep = {"input": write_exr(tmp_path / "rgb.exr", layers["<root>"]),
           "albedo": write_exr(tmp_path / "albedo.exr", layers["albedo"]),
           "normal": write_exr(tmp_path / "normal.exr", layers["sh_normal"], "XYZ"),
           "depth": write_exr(tmp_path / "depth.exr", layers["depth"][..., :1], "Z")}
    assert _run("--checkpoint", ck, "--input", aov, "--albedo", aov, "--normal", aov, "--depth", aov,
                "--out", tmp_path / "one.exr") == 0
    assert _run("--checkpoint", ck, *[x for k, p in sep.items() for x in (f"--{k}", p)],
                "--out", tmp_path / "sep.exr") == 0
    np.testing.assert_array_equal(read_exr(tmp_path / "one.exr")[0], read_exr(tmp_path / "sep.exr")[0])
    from training.denoise import _read_image
    np.testing.assert_array_equal(_read_image(str(aov), "albedo"), layers["albedo"])
    np.testing.assert_array_equal(_read_image(str(aov), "normal"), layers["sh_normal"])
    swapped = np.zeros((8, 8, 3), np.float32)
    swapped[..., 0], swapped[..., 1] = 1.0, 0.5
    write_exr(tmp_path / "layer.exr", swapped, ["albedo.R", "albedo.G", "albedo.B"])
    np.testing.assert_array_equal(_read_image(str(tmp_path / "layer.exr"), "albedo")[0, 0], [1.0, 0.5, 0.0])
    capsys.readouterr()
    assert _run("--checkpoint", ck, "--input", aov, "--albedo", aov, "--normal", aov, "--depth", sep["albedo"],
                "--out", tmp_path / "bad.exr") == 2
    err = capsys.readouterr().err
    assert f"--depth {sep['albedo']} has channels B,G,R; the depth is read from channels depth.T" in err, err
    assert not (tmp_path / "bad.exr").exists()


def test_denoise_says_when_the_inputs_sample_count_is_not_the_models(store, tmp_path, capsys):
    """A checkpoint records its training spp; ``--spp`` states an EXR's: the same count denoises silently, another
    count denoises with one warning line saying what the model expects, no count at all with one note; a
    per-sample model (any count of samples) is never warned."""
    ck = save_model(tmp_path / "nbg.pt", "nbg", store)          # trained (recorded) at 1 spp
    i = _test_frame(store)
    p = _exr_inputs(store, i, tmp_path)
    args = ["--checkpoint", ck, "--input", p["radiance"], "--albedo", p["albedo"], "--normal", p["normal"],
            "--depth", p["depth"]]
    lines = {}
    for spp in (None, 1, 4):
        capsys.readouterr()
        extra = [] if spp is None else ["--spp", spp]
        assert _run(*args, *extra, "--out", tmp_path / f"out{spp}.exr") == 0
        lines[spp] = [x for x in capsys.readouterr().err.splitlines() if x.startswith(("warning", "note"))]
    assert lines[1] == []
    assert len(lines[4]) == 1 and "1-spp" in lines[4][0] and "4 spp" in lines[4][0], lines[4]
    assert len(lines[None]) == 1 and lines[None][0].startswith("note") and "--spp" in lines[None][0]
    # a store frame composed at another count than the training one: warned; a per-sample model: never
    capsys.readouterr()
    assert _run("--checkpoint", ck, "--store", store, "--frame", i, "--spp", 2, "--out", tmp_path / "s.exr") == 0
    assert sum(x.startswith("warning") for x in capsys.readouterr().err.splitlines()) == 1
    layer = save_model(tmp_path / "layer.pt", "layer", store)
    assert _run("--checkpoint", layer, "--store", store, "--frame", i, "--spp", 1, "--out", tmp_path / "l.exr") == 0
    assert not any(x.startswith(("warning", "note")) for x in capsys.readouterr().err.splitlines())


def _exr_at(path, img, data, display):
    """``img`` (HWC float32, RGB or one channel ``Z``) as an OpenEXR file written by the OpenEXR package
    itself, with data window ``data`` and display window ``display`` (each ``(x0, y0, x1, y1)``, inclusive)."""
    import OpenEXR
    names = "RGB" if img.shape[-1] == 3 else "Z"
    box = lambda b: (np.array(b[:2], np.int32), np.array(b[2:], np.int32))      # noqa: E731
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage, "dataWindow": box(data),
              "displayWindow": box(display)}
    with OpenEXR.File(header, {c: np.ascontiguousarray(img[..., k], np.float32) for k, c in enumerate(names)}) as f:
        f.write(str(path))
    return str(path)


def _windows(path):
    import OpenEXR
    with OpenEXR.File(str(path)) as f:
        h = f.header()
        return tuple(tuple(int(v) for b in h[k] for v in b) for k in ("dataWindow", "displayWindow"))


def test_an_exrs_data_window_is_kept_and_guides_must_cover_it(store, tmp_path, capsys):
    """An input whose data window is (4,4)-(19,19) of a 24x24 display window, with guides over the whole
    display window: each guide is taken at the input's pixels, and the output keeps the input's data and
    display windows (before: written at (0,0) of a 16x16 display, the crop's place lost, exit 0; or the
    24x24 guides refused by size). The pixels are those of the same crop given as plain images. Guides at
    (0,0) that do not cover the input's pixels, or of another display window, are one line, exit 2."""
    ck = save_model(tmp_path / "wskpn.pt", "wskpn", store)
    p = _exr_inputs(store, _test_frame(store), tmp_path)
    full = {k: read_exr(v)[0][:24, :24] for k, v in p.items()}
    disp, dw = (0, 0, 23, 23), (4, 4, 19, 19)
    inp = _exr_at(tmp_path / "crop.exr", full["radiance"][4:20, 4:20], dw, disp)
    guides = {g: _exr_at(tmp_path / f"{g}-full.exr", full[g], disp, disp) for g in ("albedo", "normal", "depth")}
    args = [x for g, path in guides.items() for x in (f"--{g}", path)]
    assert _run("--checkpoint", ck, "--input", inp, *args, "--out", tmp_path / "out.exr") == 0
    assert _windows(tmp_path / "out.exr") == (dw, disp)
    plain = {g: _exr_at(tmp_path / f"{g}-plain.exr", full[g][4:20, 4:20], (0, 0, 15, 15), (0, 0, 15, 15))
             for g in ("radiance", "albedo", "normal", "depth")}
    assert _run("--checkpoint", ck, "--input", plain["radiance"], *[x for g in guides for x in (f"--{g}", plain[g])],
                "--out", tmp_path / "plain.exr") == 0
    np.testing.assert_array_equal(read_exr(tmp_path / "out.exr")[0], read_exr(tmp_path / "plain.exr")[0])
    capsys.readouterr()
    # guides of the crop's size at (0, 0) of the same display window: they hold other pixels than the input's
    at0 = {g: _exr_at(tmp_path / f"{g}-at0.exr", full[g][4:20, 4:20], (0, 0, 15, 15), disp) for g in guides}
    assert _run("--checkpoint", ck, "--input", inp, *[x for g in guides for x in (f"--{g}", at0[g])],
                "--out", tmp_path / "bad.exr") == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "(0,0)-(15,15)" in err and "(4,4)-(19,19)" in err, err
    # a guide of another display window (another render's) is refused even where its pixels would cover the input
    other = _exr_at(tmp_path / "albedo-32.exr", read_exr(p["albedo"])[0], (0, 0, 31, 31), (0, 0, 31, 31))
    assert _run("--checkpoint", ck, "--input", inp, *args, "--albedo", other, "--out", tmp_path / "bad.exr") == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "display window" in err and "32x32" in err and "24x24" in err, err
    assert not (tmp_path / "bad.exr").exists()
