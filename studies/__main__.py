"""``python -m studies scaling|bench-scale`` (see ``--help`` of each): the scaling study of
:mod:`studies.scaling`, and what a frame costs the stages that read the stores as a store grows
(:mod:`studies.bench_scale`)."""
from __future__ import annotations

import argparse
import sys

EXIT_CODES_HELP = ("exit codes: 0 done; 2 bad settings, or a store that cannot be used as asked; 3 a store is "
                   "damaged (see python -m pipeline validate); 4 a disk is full; 5 the S3 endpoint of an s3:// "
                   "store could not be reached; 130 interrupted (scaling: the same command resumes)")


def scaling_options(s: argparse.ArgumentParser) -> None:
    """The options of ``scaling``."""
    s.add_argument("--config", required=True, help="a scaling config, e.g. configs/scaling-cpu.yaml")
    s.add_argument("--out", default=None, help="folder for the stores, runs and the three files (default: the "
                                               "config's out, else data/NAME)")
    s.add_argument("--target-relmse", type=float, default=None,
                   help="the smallest number of training frames the fit predicts reaches this relMSE, with its "
                        "interval and rendering cost (pipeline estimate); refused below the fitted floor")
    s.add_argument("--target-psnr", type=float, default=None, help="the same for a PSNR (dB); refused above the "
                                                                   "fitted ceiling")
    s.add_argument("--workers", type=int, default=None, help="render workers (default: the config's, else one a core)")
    s.add_argument("--no-progress", action="store_true", help="no progress bars")


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m studies", description=__doc__, epilog=EXIT_CODES_HELP)
    sub = p.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("scaling", help="quality against the number of training frames, their scene variety and "
                                       "their share of hard cases, with fits and intervals: OUT/scaling.md, "
                                       "scaling.png, scaling.json (resumes)")
    scaling_options(s)
    s.set_defaults(fn=_scaling)
    b = sub.add_parser("bench-scale", help="what a frame costs evaluate, hard-cases, report, export and the training "
                                           "datasets as a store grows (stills, clips, pairs), in ms a frame")
    b.add_argument("--frames", nargs="+", type=int, default=None,
                   help="the store sizes to measure (default 100 1000 10000)")
    b.add_argument("--source", default=None,
                   help="the rendered store whose frames are written again (default: configs/smoke.yaml, "
                        "rendered first)")
    b.add_argument("--json", help="also write the table ({layout: {stage: {frames: ms}}}) to this file")
    b.set_defaults(fn=_bench_scale)
    return p


def _scaling(a) -> int:
    from .scaling import check_targets, load_scaling_config
    from .scaling_run import run_study
    targets = {k: v for k, v in (("relmse", a.target_relmse), ("psnr", a.target_psnr)) if v is not None}
    check_targets(targets, "--target", flags=True)
    run_study(load_scaling_config(a.config), a.out, targets=targets, workers=a.workers, progress=not a.no_progress)
    return 0


def _bench_scale(a) -> int:
    from .bench_scale import DEFAULT_FRAMES, check_frames, markdown, run
    check_frames(a.frames or DEFAULT_FRAMES, "--frames")
    res = run(frames=tuple(a.frames or DEFAULT_FRAMES), source=a.source)
    print(markdown(res))
    if a.json:
        from training.jsonio import write
        write(a.json, res)
    return 0


def main(argv=None) -> int:
    """Run a command; its exit code. Ctrl-C anywhere, the imports included, ends in one line and 130
    (``__main__`` installs :mod:`core.interrupts` first)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        return _main(argv)
    except KeyboardInterrupt:
        print(INTERRUPTED if argv[:1] == ["scaling"] else "interrupted", file=sys.stderr)
        return 130


INTERRUPTED = ("interrupted: rendered frames, finished runs and the runs' last checkpoints stay; the same command "
               "resumes")


def _main(argv) -> int:
    a = parser().parse_args(argv)
    from stores.objectstore import quiet_abandoned_requests, retry_defaults
    from training.accel import tune_allocator
    tune_allocator()
    retry_defaults()
    quiet_abandoned_requests()
    from pipeline.errors import PipelineError
    from stores.errors import StoreError, exit_status, unreachable_exit
    from training.errors import TrainingError
    from core.notices import plain_warnings
    try:
        with plain_warnings():                      # a notice (frames left out, ...) is one plain line
            return a.fn(a)
    except (TrainingError, PipelineError, StoreError) as err:
        print(f"error: {type(err).__name__}: {err}", file=sys.stderr)
        return exit_status(err, 2)
    except Exception as err:                        # an s3:// store whose endpoint is gone: 5; others raised
        return unreachable_exit(err, None, getattr(a, "out", None))


if __name__ == "__main__":
    from core import interrupts
    interrupts.install()                # before the imports: Ctrl-C from here on ends in one line
    code = main()
    interrupts.stopping()               # done: a press during the exit does nothing
    sys.exit(code)
