"""What a frame costs the stages that read the stores, as a store grows: the downstream side of
``python -m pipeline bench --only scale`` (docs/cluster.md, "Cost per frame").

``python -m studies bench-scale [--frames 100 1000 10000] [--json FILE]`` builds, at each size F,
stores of F frames: **stills** (each frame its own scene, so its own clip and scene JSON) and **clips**
(two clips of F/2 frames, one in the train split and one in the test split, their JSON the generator's
for a clip of that length: a camera a frame, ``python -m scene_gen spec --frames``). Their frames are the frames
of a small rendered store (``configs/smoke.yaml``, made by ``python -m pipeline dataset`` as a new
program), written again and again through ``stores.writer`` (the
pipeline's writer) under new scene seeds and clip ids, so the splits hold 80/10/10% of the scenes and
every frame is a real render whose content repeats; one frame in ten is tagged with a hard case
(``fireflies``, ``sun_in_view``), as the hard-case suite's frames are. The stages' cost does not depend on
what the pixels hold; rendering F frames is the other table's.

Per frame (milliseconds), at each size and layout:

- ``datasets_<kind>``: ``training.data.model_dataset`` of each input kind on the train split (its frames,
  clips or windows; the fitness screen of every frame it uses) and its first item, per train frame;
- ``evaluate``: ``training.evaluate.evaluate`` of the noisy input (metrics, no model: a model's forward
  pass costs the same at every size) on the test split, per test frame;
- ``hard_cases``: ``training.hardcases.hard_case_report`` (the noisy input on every frame, tables by case),
  per frame of the store;
- ``report``: ``training.report.report`` of a 2-step ``nbg`` run (the run, the input and OIDN on the test
  split, FLIP off), per test frame;
- ``export_<format>``: ``stores.export.export`` of the test split (whole clips) in each format, per
  exported frame. ``noisebase`` re-traces the samples with the renderer (it checks them against the
  stored ones), so it is measured on a third layout, **pairs**: F/2 clips of two frames, each the
  source store's clip itself (its seed and JSON). (A few frames of a long clip cost more a frame:
  ``layerdenoise`` scales depth by the clip's largest, so it reads every frame of the clip once.)

The table gives each stage's largest size over its smallest (the target: at most 1.5).

It is a study's, not training's: it renders (``python -m pipeline``, ``python -m scene_gen``, and the
renderer inside the noisebase export) and times training's readers, so it sits above both.
"""
from __future__ import annotations

import contextlib
import dataclasses
import io
import os
import shutil
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SMOKE = ROOT / "configs" / "smoke.yaml"
DEFAULT_FRAMES = (100, 1000, 10000)
LAYOUTS = ("stills", "clips", "pairs")
KINDS = ("samples", "pixels", "clips", "sampled-layers")
CASES = ("fireflies", "sun_in_view")


def _program(*args: str) -> str:
    """``python -m ARGS`` of this checkout as a new program (its stdout; RuntimeError with its output)."""
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    r = subprocess.run([sys.executable, "-m", *args], capture_output=True, text=True, cwd=ROOT, env=env)
    if r.returncode != 0:
        raise RuntimeError(f"python -m {' '.join(args)} failed: " + (r.stdout + r.stderr)[-2000:])
    return r.stdout


def source_store(tmp: Path) -> str:
    """``configs/smoke.yaml`` rendered into ``tmp`` by ``python -m pipeline dataset`` (a new program)."""
    out = tmp / "source.zarr"
    _program("pipeline", "dataset", "--config", str(SMOKE), "--out", str(out), "--no-progress")
    return str(out)


def _clip_json(kind: str, seed: int, frames: int) -> str:
    """A clip's scene JSON of ``frames`` frames (a camera a frame), as the scene generator writes it:
    ``python -m scene_gen spec`` as a new program."""
    return _program("scene_gen", "spec", "--kind", kind, "--seed", str(seed), "--frames", str(frames), "--res", "16")


def _scene_of(i: int, frames: int, layout: str) -> tuple[int, int, int]:
    """(scene, position in its clip, clip length) of frame ``i`` in ``layout``."""
    if layout == "stills":
        return i, 0, 1
    if layout == "pairs":
        return i // 2, i % 2, 2
    half = frames // 2
    return (0, i, half) if i < half else (1, i - half, frames - half)


def build_store(source: str, path: str, frames: int, layout: str) -> str:
    """A store of ``frames`` frames (:data:`LAYOUTS`) written from ``source``'s frames (module docstring)."""
    from stores.contract import FRAME_META
    from stores.reader import open_store, split_of_clip
    from stores.writer import open_or_create
    src = open_store(source)
    lengths = src.meta_column("num_frames")
    picks = [i for i in range(src.num_frames) if (int(lengths[i]) == 1) == (layout == "stills")]
    cache = {i: src.read_frame(i) for i in picks}
    w = open_or_create(path, dataclasses.replace(src.layout, num_frames=int(frames)),
                       {**src.config, "name": f"bench-{layout}"}, overwrite=True)
    # the long clips: one in the train split, one in the test split (a clip's id decides its split)
    long_ids = [next(c for c in range(100_000, 200_000) if split_of_clip(c) == want) for want in ("train", "test")]
    records, texts = {}, {}
    for i in range(frames):
        scene, j, n = _scene_of(i, frames, layout)
        fr = cache[picks[(i if layout == "stills" else j) % len(picks)]]
        clip_id = long_ids[scene] if layout == "clips" else 100_000 + scene
        # a pair is the source clip itself (its seed: the noisebase export re-traces its samples)
        seed = fr["meta"]["scene_seed"] if layout == "pairs" else clip_id
        if scene not in texts:          # stills and pairs: the source's own JSON
            texts[scene] = (_clip_json(str(fr["meta"]["kind"]), clip_id, n) if layout == "clips"
                            else fr["meta"]["scene_json"])
        meta = {**{k: fr["meta"][k] for k in FRAME_META}, "scene_json": texts[scene], "scene_seed": seed,
                "clip_id": clip_id, "frame": j, "num_frames": n,
                "case": CASES[(i // 10) % 2] if i % 10 == 0 else ""}
        records[i] = w.write_frame_data(i, {**fr, "meta": meta})
        if len(records) >= 512:
            w.commit(records)
            records = {}
    w.commit(records)
    return path


@contextlib.contextmanager
def _quiet():
    with contextlib.redirect_stdout(io.StringIO()), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        yield


def _timed(fn) -> float:
    t = time.perf_counter()
    with _quiet():
        fn()
    return time.perf_counter() - t


def _datasets(store: str, window: int) -> dict[str, float]:
    """Seconds of each input kind's dataset on the train split and its first item (``clips``: windows of
    ``window`` frames)."""
    from training.data import model_dataset
    from training.inputs import KINDS as INPUT_KINDS, InputSpec
    out = {}
    for kind in KINDS:
        spec = InputSpec(kind=kind, frames=window if kind == "clips" else 1)

        def build():
            ds = model_dataset(spec, store, "train", 2, 8, augment=False, seed=0)
            ds[0]
        out[kind] = _timed(build)
    assert set(KINDS) <= set(INPUT_KINDS)
    return out


def measure(store: str, run_dir: Path, tmp: Path, layout: str) -> dict[str, float]:
    """Milliseconds a frame of every stage (module docstring) on ``store`` (``pairs``: the exports only)."""
    from stores.reader import open_store
    from training.evaluate import evaluate
    from training.hardcases import hard_case_report
    from training.report import report
    if layout == "pairs":
        return _exports(store, tmp, ("noisebase",))
    st = open_store(store)
    n, train, test = st.num_frames, len(st.frames_in_split("train")), len(st.frames_in_split("test"))
    window = 2 if layout == "clips" else 1
    out = {f"datasets_{k}": 1e3 * s / max(1, train) for k, s in _datasets(store, window).items()}
    out["evaluate"] = 1e3 * _timed(lambda: evaluate("input", store, split="test", with_flip=False)) / max(1, test)
    out["hard_cases"] = 1e3 * _timed(lambda: hard_case_report([], store, tmp / "hc", oidn=False,
                                                              progress=False)) / n
    out["report"] = 1e3 * _timed(lambda: report([run_dir], store, tmp / "report", with_flip=False,
                                                progress=False)) / max(1, test)
    return {**out, **_exports(store, tmp, ("exr", "layerdenoise", "oidn"))}


def _exports(store: str, tmp: Path, formats) -> dict[str, float]:
    """Milliseconds an exported frame of each of ``formats`` (``stores.export.writers``), exporting the
    test split (whole clips: the ``layerdenoise`` depth scale and Noisebase's sequences are a clip's)."""
    from stores.export import export, writers
    from stores.reader import open_store
    frames = sorted(open_store(store).frames_in_split("test"))
    out = {}
    for fmt in formats:
        assert fmt in writers(), fmt
        dest = tmp / f"export-{fmt}"
        out[f"export_{fmt}"] = 1e3 * _timed(lambda: export(store, frames, fmt, str(dest))) / max(1, len(frames))
        shutil.rmtree(dest, ignore_errors=True)
    return out


def tiny_run(source: str, out: Path) -> Path:
    """``nbg`` trained for 2 steps on ``source`` (a checkpoint for ``report``)."""
    from training.config import TrainConfig
    from training.loop import train
    with _quiet():
        train(TrainConfig(model="nbg", steps=2, batch=2, crop=8, val_every=0, log_every=1, checkpoint_every=2),
              source, out, progress=False)
    return out


def min_frames(layouts=LAYOUTS) -> int:
    """The fewest frames a store of every layout of ``layouts`` can have: two clips of two frames or more
    (clips: the clips dataset reads windows of two) and, in stills and pairs, a clip in the train split
    and one in the test split (the datasets read the one, evaluate, report and the exports the other).
    16 for the three layouts: the first test clip of stills is frame 7, of pairs frames 14 and 15."""
    from stores.reader import split_of_clip
    f = 4
    while not all({"train", "test"} <= {split_of_clip(100_000 + _scene_of(i, f, lay)[0]) for i in range(f - f % 2)}
                  for lay in layouts if lay != "clips"):
        f += 1
    return f


def check_frames(frames, name: str = "frames", layouts=LAYOUTS) -> None:
    """``frames`` (the store sizes to measure) must be integers of at least :func:`min_frames` each
    (ConfigError naming ``name``: ``--frames`` on the command line)."""
    from core.checks import is_int, need
    from training.errors import ConfigError
    lo = min_frames(layouts)
    sizes = list(frames) if isinstance(frames, (list, tuple)) else None
    bad = [f for f in sizes or [] if not is_int(f) or f < lo]
    need(bool(sizes) and not bad, name, f"one or more integers >= {lo} (the fewest frames at which every layout has "
         "a clip in the train and the test split)", bad[0] if bad else frames, ConfigError)


def run(frames=DEFAULT_FRAMES, layouts=LAYOUTS, source: str | None = None, say=print) -> dict:
    """``{layout: {stage: {F: ms a frame}}}`` at each size, printed as it goes."""
    check_frames(frames, layouts=layouts)
    tmp = Path(tempfile.mkdtemp(prefix="bench-scale-"))
    try:
        source = source or source_store(tmp)
        run_dir = tiny_run(source, tmp / "nbg")
        table: dict = {}
        for layout in layouts:
            for f in frames:
                t0 = time.perf_counter()
                store = build_store(source, str(tmp / f"{layout}-{f}.zarr"), int(f), layout)
                built = time.perf_counter() - t0
                per = measure(store, run_dir, tmp / f"{layout}-{f}", layout)
                for stage, v in per.items():
                    table.setdefault(layout, {}).setdefault(stage, {})[int(f)] = v
                say(f"{layout} {f}: built in {built:.1f} s; " + ", ".join(f"{k} {v:.2f}" for k, v in per.items()),
                    flush=True)
                shutil.rmtree(store, ignore_errors=True)
        return table
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def markdown(table: dict) -> str:
    """The table: a row a stage and layout, ms a frame at each size, and the largest size over the smallest."""
    lines = []
    for layout, stages in table.items():
        sizes = sorted({f for v in stages.values() for f in v})
        lines += [f"| {layout} | " + " | ".join(f"{f:,}" for f in sizes) + f" | {sizes[-1]:,} / {sizes[0]:,} |",
                  "|---" * (len(sizes) + 2) + "|"]
        for stage, v in stages.items():
            ratio = v[sizes[-1]] / v[sizes[0]] if v.get(sizes[0]) else float("nan")
            lines.append(f"| {stage} | " + " | ".join(f"{v[f]:.3g}" for f in sizes) + f" | {ratio:.2f}x |")
        lines.append("")
    return "\n".join(lines)
