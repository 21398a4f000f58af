"""The commands of ``python -m scene_gen``: look at what the scene generator makes.

    python -m scene_gen preview --seed 3 --kind indoor --res 256 --spp 64 --out data/preview/indoor-3.exr
    python -m scene_gen spec --seed 3 --kind outdoor                   # the SceneSpec as JSON
    python -m scene_gen contact-sheet --count 16 --res 160 --spp 64 --out docs/contact_sheet.png
    python -m scene_gen real-scenes --out data/real-scenes              # the held-out real-scene suite's files

Previews use a fixed tone map (``core.images.display``: log(1 + x), then sRGB; no auto
exposure), so what looks right here is what the training data holds. Errors, exit codes and Ctrl-C
are :func:`core.cli.run_main`'s (a full disk is 4, as in every command).
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from scene_gen import to_mitsuba
from core.cli import Program, commands, program_parser
from scene_gen.config import ConfigError, SceneGenConfig
from scene_gen.families import family_names
from core.images import display as tonemap, write_exr, write_png
from scene_gen.sampling import sample_scene
from scene_gen.real_scenes import write_suite
from scene_gen.scene_files import load_file
from core.variant import mitsuba


def _config(path: str | None):
    if path is None:
        return SceneGenConfig()
    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"--config {path!r} does not exist")
    import yaml
    data = yaml.safe_load(p.read_text()) or {}
    if isinstance(data, dict) and "scene_gen" in data:
        data = data["scene_gen"]
    return SceneGenConfig.from_dict(data)


def render_spec(spec, *, res: int, spp: int, frame: int = 0, seed: int = 0, threads: int | None = None) -> np.ndarray:
    """Render frame ``frame`` of ``spec`` with Mitsuba's own ``mi.render`` (float32, HWC linear RGB).

    Moving objects are shown at the middle of the exposure (previews do not blur). Static objects
    sharing a material are merged, as the dataset renderer does (the same image, faster)."""
    mi = mitsuba(threads=threads)
    tau = frame + 0.5 * spec.shutter if spec.has_motion else None
    scene = to_mitsuba.load(spec, frame, res=(res, res), tau=tau, merge=True)
    img = mi.render(scene, spp=spp, seed=seed)
    return np.asarray(img, dtype=np.float32)[..., :3]


def _preview(a) -> int:
    t0 = time.perf_counter()
    spec = sample_scene(a.seed, a.kind, num_frames=a.frames, res=a.res, config=_config(a.config))
    t1 = time.perf_counter()
    img = render_spec(spec, res=a.res, spp=a.spp, frame=a.frame)
    t2 = time.perf_counter()
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    if out.suffix.lower() == ".png":
        write_png(out, img)
        written = [out]
    else:
        exr = out if out.suffix.lower() == ".exr" else out.with_suffix(".exr")
        write_exr(exr, img)
        write_png(exr.with_suffix(".png"), img)
        written = [exr, exr.with_suffix(".png")]
    if a.save_spec:
        Path(a.save_spec).write_text(spec.to_json(indent=1))
    print(f"{a.kind} seed {a.seed}: {len(spec.objects)} objects, lights "
          f"{[l.kind for l in spec.lights]} + {sum(o.emitter_radiance is not None for o in spec.objects)} area, "
          f"defocus={spec.has_defocus} motion={spec.has_motion}; sampled in {t1 - t0:.2f} s, "
          f"rendered {a.res}x{a.res}x{a.spp} spp in {t2 - t1:.1f} s, mean {float(img.mean()):.3f} -> "
          + ", ".join(map(str, written)))
    return 0


def _spec(a) -> int:
    spec = sample_scene(a.seed, a.kind, num_frames=a.frames, res=a.res, config=_config(a.config))
    print(spec.to_json(indent=1))
    return 0


def _contact_sheet(a) -> int:
    from PIL import Image, ImageDraw

    cfg = _config(a.config)
    kinds = family_names()
    cols = a.cols or int(np.ceil(np.sqrt(a.count)))
    rows = int(np.ceil(a.count / cols))
    pad = 2
    sheet = Image.new("RGB", (cols * (a.res + pad) + pad, rows * (a.res + pad) + pad), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    for i in range(a.count):
        kind = kinds[i % len(kinds)]
        seed = a.seed + i // len(kinds)
        spec = sample_scene(seed, kind, res=a.res, config=cfg)
        img = render_spec(spec, res=a.res, spp=a.spp)
        tile = Image.fromarray((tonemap(img) * 255 + 0.5).astype(np.uint8))
        x, y = pad + (i % cols) * (a.res + pad), pad + (i // cols) * (a.res + pad)
        sheet.paste(tile, (x, y))
        flags = ("D" if spec.has_defocus else "") + ("M" if spec.has_motion else "")
        draw.text((x + 3, y + 2), f"{kind} {seed} {flags}", fill=(255, 255, 255))
        print(f"[{i + 1}/{a.count}] {kind} seed {seed}: {len(spec.objects)} objects", flush=True)
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    # a 256-colour palette keeps the README's image small (a quarter of the RGB file)
    sheet.quantize(colors=256, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE).save(out, optimize=True)
    print(f"wrote {out}")
    return 0


def _real_scenes(a) -> int:
    t0 = time.perf_counter()
    paths = write_suite(a.out)
    print(f"wrote {len(paths)} scene files in {time.perf_counter() - t0:.1f} s (each loads with mi.load_file): "
          + ", ".join(str(p) for p in paths))
    if a.preview:
        for p in paths:
            img = np.asarray(mitsuba().render(load_file(p), spp=a.preview), np.float32)[..., :3]
            write_png(p.with_suffix(".png"), img)
        print(f"previews: {len(paths)} PNGs beside them ({a.preview} spp, the files' own sensors)")
    return 0


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    p = program_parser("python -m scene_gen", "Random scenes for denoiser training data.")
    sub = commands(p)

    def common(sp, res):
        sp.add_argument("--seed", type=int, default=0, help="scene seed (default 0)")
        sp.add_argument("--res", type=int, default=res, help=f"image width and height in pixels (default {res})")
        sp.add_argument("--config", help="YAML with scene_gen settings (a 'scene_gen' section or the settings themselves)")

    pv = sub.add_parser("preview", help="render one scene to EXR and a tone-mapped PNG")
    common(pv, 256)
    pv.add_argument("--kind", choices=family_names(), default="indoor", help="scene family (default indoor)")
    pv.add_argument("--spp", type=int, default=64, help="samples per pixel (default 64)")
    pv.add_argument("--frames", type=int, default=1, help="frames in the clip (default 1)")
    pv.add_argument("--frame", type=int, default=0, help="which frame to render (default 0)")
    pv.add_argument("--out", required=True, help="file.exr (writes a .png beside it) or file.png")
    pv.add_argument("--save-spec", help="also write the SceneSpec JSON here")
    pv.set_defaults(run=_preview)

    sp = sub.add_parser("spec", help="print the SceneSpec JSON of one scene")
    common(sp, 256)
    sp.add_argument("--kind", choices=family_names(), default="indoor", help="scene family (default indoor)")
    sp.add_argument("--frames", type=int, default=1)
    sp.set_defaults(run=_spec)

    cs = sub.add_parser("contact-sheet", help="a PNG grid of random scenes of every family")
    common(cs, 160)
    cs.add_argument("--count", type=int, default=16, help="number of scenes, the families in turn (default 16)")
    cs.add_argument("--cols", type=int, default=0, help="columns (default: square)")
    cs.add_argument("--spp", type=int, default=64)
    cs.add_argument("--out", default="docs/contact_sheet.png")
    cs.set_defaults(run=_contact_sheet)

    rs = sub.add_parser("real-scenes", help="write the held-out real-scene suite's Mitsuba scene files "
                        "(scene_gen.real_scenes; configs/real-scenes.yaml renders them)")
    rs.add_argument("--out", default="data/real-scenes", help="folder for the files (default data/real-scenes)")
    rs.add_argument("--preview", type=int, default=0, metavar="SPP",
                    help="also render each file through its own sensor at SPP samples to a PNG beside it")
    rs.set_defaults(run=_real_scenes)
    return p


def check_counts(args) -> None:
    """Counts a command takes are >= 1, and ``--frame`` lies in the clip: else a ConfigError (exit 2)."""
    for name in ("res", "spp", "count", "frames"):
        v = getattr(args, name, None)
        if v is not None and v < 1:
            raise ConfigError(f"--{name} must be >= 1, got {v}")
    if hasattr(args, "frame") and not 0 <= args.frame < args.frames:
        raise ConfigError(f"--frame must lie in [0, {args.frames - 1}], got {args.frame}")


# a library's ValueError (a scene file Mitsuba refuses) or a file that cannot be written: one line, exit 2
PROGRAM = Program(parser=build_parser, setup=check_counts, bad_input=(ValueError, OSError))
