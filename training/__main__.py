"""``python -m training train|evaluate|report|bench|fma`` (see ``--help`` of each)."""
from __future__ import annotations

import argparse
import json
import sys


def _train(a) -> int:
    from .config import TrainConfig
    from .loop import train
    cfg = TrainConfig(model=a.model, model_cfg=json.loads(a.model_cfg), loss=a.loss, lr=a.lr, batch=a.batch,
                      crop=a.crop, spp=a.spp, steps=a.steps, seed=a.seed, val_every=a.val_every,
                      val_frames=a.val_frames, checkpoint_every=a.checkpoint_every, device=a.device)
    res = train(cfg, a.store, a.out, progress=not a.no_progress)
    print(json.dumps(res, default=float))
    return 0


def _evaluate(a) -> int:
    from .evaluate import evaluate, write_json
    res = evaluate(a.checkpoint, a.store, split=a.split, spp=a.spp, max_frames=a.frames, with_flip=not a.no_flip)
    write_json(res, a.out)
    print(json.dumps({"method": res["method"], **res["mean"]}, default=float))
    return 0


def _report(a) -> int:
    from .report import report
    report(a.runs, a.store, a.out, split=a.split, spp=a.spp, max_frames=a.frames, with_flip=not a.no_flip)
    print(f"wrote {a.out}/report.md")
    return 0


def _bench(a) -> int:
    from .bench import run
    run(size=a.size, spp=a.spp, repeats=a.repeats)
    return 0


def _fma(a) -> int:
    from .fma import figure10, figure10_markdown
    print(figure10_markdown(figure10()))
    return 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m training", description=__doc__)
    sub = p.add_subparsers(dest="cmd", required=True)

    t = sub.add_parser("train", help="train a denoiser; writes OUT/checkpoint.pt and OUT/metrics.csv (resumes)")
    t.add_argument("--model", required=True)
    t.add_argument("--store", required=True)
    t.add_argument("--out", required=True)
    t.add_argument("--steps", type=int, default=1000)
    t.add_argument("--crop", type=int, default=128)
    t.add_argument("--batch", type=int, default=4)
    t.add_argument("--spp", type=int, default=8)
    t.add_argument("--lr", type=float, default=0.005)
    t.add_argument("--loss", default="smape")
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--val-every", type=int, default=100)
    t.add_argument("--val-frames", type=int, default=8)
    t.add_argument("--checkpoint-every", type=int, default=100)
    t.add_argument("--device", default="cpu")
    t.add_argument("--model-cfg", default="{}", help='JSON model settings, e.g. \'{"layers": 3}\'')
    t.add_argument("--no-progress", action="store_true")
    t.set_defaults(fn=_train)

    e = sub.add_parser("evaluate", help="per-frame and mean metrics with ms per megapixel, as JSON")
    e.add_argument("--checkpoint", required=True, help="a checkpoint.pt, or 'input' / 'oidn' for a baseline")
    e.add_argument("--store", required=True)
    e.add_argument("--split", default="test")
    e.add_argument("--spp", type=int, default=8)
    e.add_argument("--frames", type=int, default=0, help="at most this many frames (0: all)")
    e.add_argument("--out", required=True)
    e.add_argument("--no-flip", action="store_true")
    e.set_defaults(fn=_evaluate)

    r = sub.add_parser("report", help="evaluate runs and baselines; Markdown table, plot and crops")
    r.add_argument("--runs", nargs="+", required=True)
    r.add_argument("--store", required=True)
    r.add_argument("--out", required=True)
    r.add_argument("--split", default="test")
    r.add_argument("--spp", type=int, default=8)
    r.add_argument("--frames", type=int, default=0)
    r.add_argument("--no-flip", action="store_true")
    r.set_defaults(fn=_report)

    b = sub.add_parser("bench", help="inference ms per megapixel of every model and OIDN")
    b.add_argument("--size", type=int, default=128)
    b.add_argument("--spp", type=int, default=8)
    b.add_argument("--repeats", type=int, default=3)
    b.set_defaults(fn=_bench)

    f = sub.add_parser("fma", help="figure 10: FMAs against spp")
    f.set_defaults(fn=_fma)

    a = p.parse_args(argv)
    from stores.errors import StoreError

    from .errors import TrainingError
    try:
        return a.fn(a)
    except (TrainingError, StoreError) as err:
        print(f"error: {type(err).__name__}: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
