"""``python -m pipeline dataset``: build a dataset from a YAML config on a Dask cluster (the library call is
:func:`pipeline.dataset.run_dataset`; this prints its lines and summary).

    python -m pipeline dataset --config configs/default.yaml [--out PATH] [--scheduler ADDR] [--workers N]

The config is loaded and checked first (unknown keys and bad values: exit 2 with the field named); the
run prints the cluster and its dashboard address, follows the frames with a progress bar, and ends with
the summary: store path, frames, elapsed time, dashboard address, validation. Ctrl-C stops the run in one
line on stderr (``interrupted: complete frames stay in STORE; ...``); re-running the same command
finishes the others. Exit codes (``core.cli``): 0 all frames complete and the store valid, 1 some frames
failed or the validator found problems, 2 bad config / unreachable cluster, 130 interrupted.
"""
from __future__ import annotations

import json
from pathlib import Path

from pipeline.config import load_config
from pipeline.dataset import run_dataset
from pipeline.errors import ConfigError

DEFAULT_CONFIG = "configs/default.yaml"


def _say(line: str) -> None:
    print(line, flush=True)


def add_arguments(p) -> None:
    p.add_argument("--config", default=DEFAULT_CONFIG, help=f"dataset YAML (default: {DEFAULT_CONFIG})")
    p.add_argument("--out", help="store path or URL (default: the config's out, else $DENOISE_DATA/<name>.zarr)")
    p.add_argument("--scheduler", help="address of a running Dask scheduler (tcp://host:8786) instead of a "
                                       "LocalCluster")
    p.add_argument("--workers", type=int, help="LocalCluster workers (default: one per core) or batch jobs")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="set a config field (a dotted path, the value read as YAML), e.g. --set render.filter=gaussian "
                        "--set name=real-scenes-gaussian; repeatable")
    p.add_argument("--no-progress", action="store_true", help="no progress bar (logs only)")
    p.add_argument("--summary-json", help="also write the run summary to this JSON file")
    p.add_argument("--overwrite", action="store_true",
                   help="delete whatever is at the store path first (another store, a store of another config, "
                        "a folder that is not a store) and build from scratch; without it such a path is refused")


def run(args) -> int:
    if args.workers is not None and not 1 <= args.workers <= 4096:
        raise ConfigError(f"--workers must be an integer in [1, 4096] (LocalCluster processes, or batch jobs), "
                          f"got {args.workers}")
    cfg = load_config(args.config, args.set)
    summary = run_dataset(cfg, out=args.out, scheduler=args.scheduler, workers=args.workers,
                          progress=not args.no_progress, overwrite=args.overwrite, say=_say)
    print_summary(summary)
    if args.summary_json:
        Path(args.summary_json).write_text(json.dumps(summary, indent=2, default=str))
    return 0 if summary["ok"] else 1


def print_summary(s: dict) -> None:
    """The closing lines of a run (its ``summary``), then its ``time:`` line where frames were rendered."""
    _say("")
    _say(f"store:      {s['store']}")
    _say(f"frames:     {s['complete']}/{s['frames']} complete ({s['rendered']} rendered now, {s['skipped']} "
         f"skipped, {len(s['failed'])} failed)")
    for idx, err in sorted(s["failed"].items()):
        _say(f"  frame {idx} failed: {err}")
    _say(f"elapsed:    {s['elapsed_s']:.1f} s (render time {s['render_s']:.1f} s summed over tasks)")
    _say(f"dashboard:  {s['dashboard'] or 'none'}")
    v = s["validation"]
    _say(f"validation: {'ok' if v.get('ok') else ('not run' if v.get('ok') is None else 'PROBLEMS')}"
         f" ({v.get('frames_checked', 0)} frame(s) written now; `python -m pipeline validate` reads every frame)"
         + ("".join(f"\n  {p}" for p in v.get("problems", [])[:20]) if not v.get("ok") else ""))
    t = s.get("timings")
    if t:
        _say(f"time:       start {t['start_s']:.1f} s, cluster {t['cluster_start_s']:.1f} s up and "
             f"{t['cluster_close_s']:.1f} s down, frames {t.get('frames_s', 0.0):.1f} s (render "
             f"{s['render_s']:.1f} s, of which scene loads {t['load_s']:.1f} s, and writes {t['write_s']:.1f} s "
             f"summed over tasks), validation {t['validate_s']:.1f} s")
