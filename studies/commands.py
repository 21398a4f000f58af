"""The commands of ``python -m studies``: ``scaling`` (the scaling study of :mod:`studies.scaling`) and
``bench-scale`` (what a frame costs the stages that read the stores as a store grows,
:mod:`studies.bench_scale`). Errors, exit codes and Ctrl-C are :func:`core.cli.run_main`'s."""
from __future__ import annotations

import argparse

from core.cli import Program, commands, program_parser
from stores.commands import explain


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
    s.add_argument("--models", default=None, help="only these models' runs (labels, comma-separated; the "
                                                   "others are left as they are): a study stopped early reports "
                                                   "the models it has finished")
    s.add_argument("--no-progress", action="store_true", help="no progress bars")


def parser(argv=None) -> argparse.ArgumentParser:
    p = program_parser("python -m studies", "What both renders and trains: the scaling study and bench-scale.")
    sub = commands(p, dest="cmd")
    s = sub.add_parser("scaling", help="quality against the number of training frames, their scene variety and "
                                       "their share of hard cases, with fits and intervals: OUT/scaling.md, "
                                       "scaling.png, scaling.json (resumes)")
    scaling_options(s)
    s.set_defaults(run=_scaling)
    b = sub.add_parser("bench-scale", help="what a frame costs evaluate, hard-cases, report, export and the training "
                                           "datasets as a store grows (stills, clips, pairs), in ms a frame")
    b.add_argument("--frames", nargs="+", type=int, default=None,
                   help="the store sizes to measure (default 100 1000 10000)")
    b.add_argument("--source", default=None,
                   help="the rendered store whose frames are written again (default: configs/smoke.yaml, "
                        "rendered first)")
    b.add_argument("--json", help="also write the table ({layout: {stage: {frames: ms}}}) to this file")
    b.set_defaults(run=_bench_scale)
    return p


def _scaling(a) -> int:
    from .scaling import check_targets, load_scaling_config
    from .scaling_run import run_study
    targets = {k: v for k, v in (("relmse", a.target_relmse), ("psnr", a.target_psnr)) if v is not None}
    check_targets(targets, "--target", flags=True)
    scfg = load_scaling_config(a.config)
    if a.models is not None:
        scfg = scfg.only_models([m.strip() for m in a.models.split(",") if m.strip()])
    run_study(scfg, a.out, targets=targets, workers=a.workers, progress=not a.no_progress)
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


INTERRUPTED = ("rendered frames, finished runs and the runs' last checkpoints stay; the same command "
               "resumes")


def setup(args) -> None:
    from stores.commands import setup as store_setup
    from training.accel import tune_allocator
    tune_allocator()
    store_setup(args)


PROGRAM = Program(parser=parser, setup=setup, explain=explain,
                  interrupted=lambda err, args, argv: INTERRUPTED if argv[:1] == ["scaling"] else "")
