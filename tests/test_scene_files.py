"""A user's Mitsuba scene file as a scene source (``scene_gen.scene_files``, ``file:`` groups of a dataset
config): the frames of a file no generator wrote render like generated ones, against Mitsuba's own
``aov`` integrator and ``mi.render`` of the file as oracles; the file's path and hash are recorded; bad
files, a missing sensor and a changed file are one line; the store is the same bytes on 1 and 2 workers
and validates, trains and evaluates like any other."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from stores.contract import FEATURE_GROUPS as G

ROOT = Path(__file__).resolve().parent.parent
RES = (32, 24)

SCENE = """<scene version="3.0.0">
  <integrator type="path"><integer name="max_depth" value="5"/></integrator>
  <sensor type="perspective">
    <float name="fov" value="45"/>
    <transform name="to_world"><lookat origin="0, 1.3, 4" target="0, 0.5, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="{w}"/><integer name="height" value="{h}"/>
      <rfilter type="box"/></film>
  </sensor>
  <bsdf type="diffuse" id="checker">
    <texture type="bitmap" name="reflectance"><string name="filename" value="textures/checker.png"/></texture>
  </bsdf>
  <shape type="rectangle" id="floor">
    <transform name="to_world"><rotate x="1" angle="-90"/><scale value="4"/></transform>
    <ref id="checker"/>
  </shape>
  <shape type="rectangle" id="wall">
    <transform name="to_world"><scale value="4"/><translate z="-2"/></transform>
    <bsdf type="diffuse"><rgb name="reflectance" value="0.55, 0.5, 0.45"/></bsdf>
  </shape>
  <shape type="sphere" id="gold">
    <point name="center" x="-0.7" y="0.5" z="0"/><float name="radius" value="0.5"/>
    <bsdf type="roughconductor"><string name="material" value="Au"/><float name="alpha" value="0.2"/></bsdf>
  </shape>
  <shape type="sphere" id="glass">
    <point name="center" x="0.7" y="0.45" z="0.3"/><float name="radius" value="0.45"/>
    <bsdf type="dielectric"><float name="int_ior" value="1.5"/></bsdf>
  </shape>
  <shape type="rectangle" id="lamp">
    <transform name="to_world"><rotate x="1" angle="90"/><scale value="0.6"/><translate y="2.6"/></transform>
    <emitter type="area"><rgb name="radiance" value="12"/></emitter>
  </shape>
  <emitter type="constant"><rgb name="radiance" value="0.15"/></emitter>
</scene>
"""


def write_scene(folder: Path, *, sensor: bool = True, extra: str = "", res=RES) -> Path:
    """The test's scene file (bitmap texture, area light, rough conductor, dielectric) and its texture."""
    from core.variant import mitsuba
    mi = mitsuba()
    (folder / "textures").mkdir(parents=True, exist_ok=True)
    y, x = np.mgrid[0:32, 0:32]
    img = np.where(((x // 8) + (y // 8)) % 2 == 0, 0.8, 0.15)[..., None] * np.array([1.0, 0.9, 0.7])
    mi.Bitmap(np.ascontiguousarray((img * 255).astype(np.uint8))).write(str(folder / "textures" / "checker.png"))
    text = SCENE.format(w=res[0], h=res[1])
    if not sensor:
        a, b = text.index("  <sensor"), text.index("</sensor>") + len("</sensor>\n")
        text = text[:a] + text[b:]
    text = text.replace("</scene>", extra + "</scene>")
    path = folder / "room.xml"
    path.write_text(text)
    return path


def file_config(tmp_path, path, **kw) -> dict:
    d = {"name": "files", "seed": 11, "resolution": list(RES),
         "scenes": [{"file": str(path), "count": 3, "camera": {"jitter": 0.0, "turn": 0.0, "zoom": 0.0}},
                    {"file": str(path), "count": 1, "frames": 3}],
         "render": {"spp": 4, "layer_levels": 2, "ref_spp": 64, "ref_passes": 4, "ref_min_passes": 2},
         "split": {"train": 0.5, "test": 0.5}, "cluster": {"dashboard_address": None}}
    d.update(kw)
    return d


def run_cli(*args, timeout=600):
    return subprocess.run([sys.executable, "-m", *args], cwd=ROOT, capture_output=True, text=True, timeout=timeout)


def dataset(tmp_path, cfg: dict, out: str, *extra):
    import yaml
    p = tmp_path / f"{out}.yaml"
    p.write_text(yaml.safe_dump(cfg))
    return run_cli("pipeline", "dataset", "--config", str(p), "--out", str(tmp_path / f"{out}.zarr"),
                   "--no-progress", *extra)


# -------------------------------------------------------------------------------------------------
def test_file_frame_matches_mitsubas_aov_and_render(mi, tmp_path):
    """Frame 0 of a file's scene seen through the file's own sensor (no jitter): its per-pixel albedo and
    normal guides are those of Mitsuba's ``aov`` integrator on the file (equal where every sample of a pixel
    sees one flat untextured surface, else within 3 standard errors), its specular colour and roughness
    are the file's BSDFs' (gold's F0, glass's F0, sqrt(alpha)), and its reference is ``mi.render`` of the
    file within its standard errors."""
    from pipeline.render import RenderConfig, render_frame
    from scene_gen import scene_files as sf
    path = write_scene(tmp_path)
    settings = sf.CameraSettings(jitter=0.0, turn=0.0, zoom=0.0)
    spec = sf.file_spec(path, sf.content_hash(path), sf.inspect(path, settings), settings, 5, 1)
    assert spec.kind == "file" and spec.source.path == str(path.resolve()) and spec.max_depth == 4
    out = render_frame(spec, 0, RenderConfig(res=RES, spp=64, layer_levels=1, ref_spp=1024, ref_passes=16))
    assert out["meta"]["kind"] == "file" and json.loads(out["meta"]["scene_json"])["source"]["sha256"] == spec.source.sha256
    f = out["features"].astype(np.float64)
    scene = mi.load_file(str(path))
    aov = mi.load_dict({"type": "aov", "aovs": "albedo:albedo,nn:sh_normal"})
    runs = np.stack([np.asarray(mi.render(scene, integrator=aov, spp=64, seed=s), np.float64) for s in range(4)])
    names = list(aov.aov_names())                   # the last channels of the image, in this order
    ch = {n: runs.shape[-1] - len(names) + i for i, n in enumerate(names)}
    # Mitsuba's eval_diffuse_reflectance of a glossy conductor varies with the view and exceeds 1 (pi times
    # its BSDF at the normal); the feature clips each sample to [0, 1], so a pixel that sees gold has no
    # oracle in the aov's mean (it is checked where exact: every sample clipped to 1)
    gold_seen = np.isclose(f[..., G["roughness"]], np.sqrt(0.2), atol=1e-6)[..., 0].any(-1)
    for guide, sl, keys in (("albedo", G["albedo"], ("albedo.R", "albedo.G", "albedo.B")),
                            ("normal", G["normal"], ("nn.X", "nn.Y", "nn.Z"))):
        mine = out[f"guides_{guide}"].astype(np.float64)
        theirs = runs[..., [ch[k] for k in keys]]
        want = np.clip(theirs.mean(0), 0.0, 1.0) if guide == "albedo" else theirs.mean(0)
        v1 = f[..., sl].var(axis=2, ddof=1)          # one sample's variance, the same distribution on both sides
        var = v1 / 64 + v1 / (4 * 64)
        # every sample of the pixel saw one value, on both sides (a pixel at a silhouette is not exact)
        exact = (np.ptp(f[..., sl], axis=2).max(-1) < 1e-6) & (theirs.std(0).max(-1) < 1e-6)
        assert exact.sum() > 0.3 * exact.size, guide
        np.testing.assert_allclose(mine[exact], want[exact], atol=2e-5, err_msg=guide)
        rest = ~exact & ~gold_seen
        z = np.abs(mine - want)[rest] / np.sqrt(var[rest] + 1e-12)
        assert rest.sum() > 50 and np.mean(z > 3) < 0.02, (guide, rest.sum(), np.mean(z > 3))
    # materials asked of the BSDFs
    spec_c, rough = f[..., G["specular"]].reshape(-1, 3), f[..., G["roughness"]].reshape(-1)
    gold_f0 = ((np.array([0.143, 0.3753, 1.442]) - 1) ** 2 + np.array([3.983, 2.3856, 1.6034]) ** 2) / (
        (np.array([0.143, 0.3753, 1.442]) + 1) ** 2 + np.array([3.983, 2.3856, 1.6034]) ** 2)
    gold = np.isclose(rough, np.sqrt(0.2), atol=1e-6)
    assert gold.sum() > 50
    np.testing.assert_allclose(spec_c[gold], np.broadcast_to(gold_f0, (gold.sum(), 3)), atol=2e-3)
    glass = (rough == 0) & (f[..., 3].reshape(-1) > 0)
    assert glass.sum() > 30
    np.testing.assert_allclose(spec_c[glass], ((1.5 / 1.000277 - 1) / (1.5 / 1.000277 + 1)) ** 2, atol=1e-6)
    # the reference against plain mi.render of the file (its own integrator, sensor and film)
    passes = np.stack([np.asarray(mi.render(scene, spp=512, seed=100 + s), np.float64)[..., :3] for s in range(4)])
    ref, se = out["reference"].astype(np.float64), out["reference_stderr"].astype(np.float64)
    z = (ref - passes.mean(0)) / np.sqrt(se ** 2 + passes.var(0, ddof=1) / 4 + 1e-12)
    assert np.mean(np.abs(z) > 3) < 0.02 and abs(z.mean()) < 0.25, (np.mean(np.abs(z) > 3), z.mean())
    zimg = (ref.mean((0, 1)) - passes.mean(0).mean((0, 1))) / np.sqrt((se ** 2).sum((0, 1)) / ref[..., 0].size ** 2
                                                                      + passes.mean((1, 2)).var(0, ddof=1) / 4)
    assert np.all(np.abs(zimg) < 3), zimg


def test_cameras_vary_around_the_sensor_and_clips_move(tmp_path):
    """Stills draw cameras near the file's sensor from the scene's seed (the same seed, the same cameras);
    a clip's camera travels, so its frames after the first carry motion vectors."""
    from scene_gen import scene_files as sf
    path = write_scene(tmp_path)
    s = sf.CameraSettings()
    info = sf.inspect(path, s)
    base = np.asarray(info["camera"]["origin"])
    h = sf.content_hash(path)
    a, b, c = (sf.file_spec(path, h, info, s, seed, 1) for seed in (1, 1, 2))
    assert a == b and a != c
    for sp in (a, c):
        assert 0 < np.linalg.norm(np.asarray(sp.cameras[0].origin) - base) <= s.jitter * info["distance"] + 1e-9
    clip = sf.file_spec(path, h, info, s, 3, 4)
    steps = np.diff([cam.origin for cam in clip.cameras], axis=0)
    assert np.allclose(np.linalg.norm(steps, axis=1), s.move * info["distance"] / 3)
    from pipeline.render import RenderConfig, render_frame
    out = render_frame(clip, 2, RenderConfig(res=(16, 12), spp=2, layer_levels=1, ref_spp=0, ref_passes=2,
                                             ref_min_passes=2))
    assert np.abs(out["guides_motion"]).max() > 0.05 and not out["meta"]["has_motion"]


def test_bad_files_are_one_line(tmp_path):
    """A file that does not parse, one with a plugin Mitsuba lacks, one without a sensor (and no camera:), a
    missing file and a resume after the file changed: each exits 2 with one line naming the file."""
    good = write_scene(tmp_path / "good")
    cases = {
        "not XML": (write_scene(tmp_path / "broken", extra="<shape type='sphere'>"), "is not valid XML"),
        "plugin": (write_scene(tmp_path / "plugin", extra="<bsdf type='nosuchbsdf' id='x'/>"), "nosuchbsdf"),
        "no sensor": (write_scene(tmp_path / "nosensor", sensor=False), "has no sensor"),
        "missing": (tmp_path / "nowhere.xml", "does not exist"),
    }
    for name, (path, words) in cases.items():
        r = dataset(tmp_path, file_config(tmp_path, path), name.replace(" ", "-"))
        lines = [x for x in r.stderr.splitlines() if x.strip()]
        assert r.returncode == 2 and len(lines) == 1 and words in lines[0] and str(Path(path).name) in lines[0], (
            name, r.returncode, r.stderr[-2000:])
    # a scene without a sensor renders once its group gives a camera
    nosensor = cases["no sensor"][0]
    cfg = file_config(tmp_path, nosensor, render={"spp": 1, "layer_levels": 1, "ref_spp": 8, "ref_passes": 2,
                                                  "ref_min_passes": 2}, resolution=[8, 8])
    cfg["scenes"] = [{"file": str(nosensor), "count": 1, "camera": {"origin": [0, 1, 4], "target": [0, 0.5, 0]}}]
    r = dataset(tmp_path, cfg, "with-camera")
    assert r.returncode == 0, r.stderr[-2000:]
    # a changed file (here: its texture) refuses the resume in one line
    cfg = file_config(tmp_path, good, render={"spp": 1, "layer_levels": 1, "ref_spp": 8, "ref_passes": 2,
                                              "ref_min_passes": 2}, resolution=[8, 8])
    cfg["scenes"] = cfg["scenes"][:1]
    assert dataset(tmp_path, cfg, "resume").returncode == 0
    tex = good.parent / "textures" / "checker.png"
    tex.write_bytes(tex.read_bytes() + b"\0")
    r = dataset(tmp_path, cfg, "resume")
    lines = [x for x in r.stderr.splitlines() if x.strip()]
    assert r.returncode == 2 and len(lines) == 1 and "changed" in lines[0] and "room.xml" in lines[0], r.stderr


@pytest.mark.timeout(900)
def test_a_file_store_is_reproducible_and_trains_like_any_other(tmp_path):
    """The same config on 1 and 2 workers gives the same arrays; the store validates (frames/kind 'file',
    the file's path and hash in each scene's JSON), trains a few steps and evaluates."""
    import zarr
    path = write_scene(tmp_path)
    cfg = file_config(tmp_path, path)
    for n in (1, 2):
        r = dataset(tmp_path, cfg, f"w{n}", "--workers", str(n))
        assert r.returncode == 0, r.stderr[-3000:]
    a, b = (zarr.open_group(str(tmp_path / f"w{n}.zarr"), mode="r") for n in (1, 2))
    for name in ("inputs/radiance", "inputs/features", "layers/radiance", "reference/radiance", "reference/stderr",
                 "guides/albedo", "guides/motion", "frames/scene_json"):
        assert np.array_equal(a[name][:], b[name][:]), name
    assert list(a["frames/kind"][:]) == ["file"] * 6
    specs = [json.loads(t) for t in a["frames/scene_json"][:] if t]
    assert {s["source"]["path"] for s in specs} == {str(path.resolve())} and len(specs) == 4
    r = run_cli("pipeline", "validate", str(tmp_path / "w1.zarr"))
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    run = tmp_path / "run"
    r = run_cli("training", "train", "--model", "nbg", "--store", str(tmp_path / "w1.zarr"), "--steps", "3",
                "--crop", "16", "--batch", "2", "--out", str(run))
    assert r.returncode == 0, r.stderr[-3000:]
    r = run_cli("training", "evaluate", "--checkpoint", str(run / "checkpoint.pt"), "--store",
                str(tmp_path / "w1.zarr"), "--split", "test", "--no-flip", "--out", str(tmp_path / "eval.json"))
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    ev = json.loads((tmp_path / "eval.json").read_text())
    assert ev["frames"] and all(np.isfinite(fr["relmse"]) for fr in ev["frames"])
    # the real-scene table on it: the run against its own input and OIDN, per scene file, with intervals
    r = run_cli("training", "real-scenes", "--runs", str(run), "--store", str(tmp_path / "w1.zarr"),
                "--out", str(tmp_path / "rs"))
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    res = json.loads((tmp_path / "rs" / "real-scenes.json").read_text())[0]
    assert set(res["scenes"]) == {"(all)", "room"} and res["filter"] == "box"
    cell = res["scenes"]["room"]["run"]
    assert cell["vs_input"]["input"] == "input" and cell["vs_oidn"]["input"] == "oidn"
    assert cell["relmse_ci95"] is not None and 0 < cell["mean_ratio"] < 10
    md = (tmp_path / "rs" / "real-scenes.md").read_text()
    assert "Against its own noisy input" in md and "Against OIDN" in md


def test_a_file_with_exr_textures_loads_in_a_one_thread_worker(tmp_path):
    """An EXR texture loads where drjit's pool has one thread (a Dask worker's): Mitsuba's OpenEXR reader
    waits on the pool's other thread, so without ``scene_files.load_file`` raising the pool for the load this
    hung forever (run in its own process, with a timeout)."""
    from core.images import write_exr
    path = write_scene(tmp_path)
    write_exr(tmp_path / "textures" / "checker.exr", np.full((8, 8, 3), 0.5, np.float32))
    path.write_text(path.read_text().replace("textures/checker.png", "textures/checker.exr"))
    code = ("import drjit as dr; from core.variant import mitsuba; mitsuba(threads=1); "
            "from scene_gen.scene_files import load_file; "
            f"s = load_file({str(path)!r}); print(len(s.shapes()), dr.thread_count())")
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and r.stdout.split() == ["5", "1"], r.stdout + r.stderr[-2000:]


def test_what_a_file_names_is_found_and_hashed_as_mitsuba_finds_it(mi, tmp_path):
    """``<default>`` parameters, ``<path>`` folders and a texture named through them are found and hashed (a
    changed texture changes the hash, a file cache or not); a parameter without a default, a name found
    nowhere, a mirrored sensor and a scene past the far clip plane are one-line errors."""
    from core.images import write_exr
    from scene_gen import scene_files as sf
    from scene_gen.errors import SceneFileError
    path = write_scene(tmp_path)
    (tmp_path / "maps").mkdir()
    write_exr(tmp_path / "maps" / "grey.exr", np.full((4, 4, 3), 0.5, np.float32))
    text = path.read_text().replace('<scene version="3.0.0">', '<scene version="3.0.0">\n  <default name="tex" value="grey"/>\n  <path value="maps"/>')
    text = text.replace("textures/checker.png", "$tex.exr")
    path.write_text(text)
    assert tmp_path / "maps" / "grey.exr" in sf.referenced_files(path)
    mi.load_file(str(path))                                  # Mitsuba finds it the same way
    before = sf.content_hash(path)
    write_exr(tmp_path / "maps" / "grey.exr", np.full((4, 4, 3), 0.25, np.float32))
    assert sf.content_hash(path) != before
    for bad, words in ((text.replace('<default name="tex" value="grey"/>', ""), "without a <default>"),
                       (text.replace('<path value="maps"/>', ""), "neither in its folder")):
        path.write_text(bad)
        with pytest.raises(SceneFileError, match=words):
            sf.content_hash(path)
    mirrored = write_scene(tmp_path / "m")
    mirrored.write_text(mirrored.read_text().replace('<lookat origin="0, 1.3, 4"', '<scale x="-1"/><lookat origin="0, 1.3, 4"'))
    with pytest.raises(SceneFileError, match="mirrors the image"):
        sf.inspect(mirrored, sf.CameraSettings())
    huge = write_scene(tmp_path / "h")
    huge.write_text(huge.read_text().replace('<scale value="4"/><translate z="-2"/>', '<scale value="40000"/><translate z="-2"/>'))
    with pytest.raises(SceneFileError, match="far clip"):
        sf.inspect(huge, sf.CameraSettings())
