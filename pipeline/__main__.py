"""``python -m pipeline COMMAND``: render-frame, dataset, validate, export, estimate, bench.

Each sub-command lives in its own module with ``add_arguments(parser)`` and ``run(args) -> int``;
this file only dispatches and turns library errors into one-line messages and exit codes, the same
for every command (``EXIT_CODES_HELP``): 0 ok; 1 problems found or frames failed; 2 bad input (a bad
config or argument, a path that is not a readable store, an unreachable cluster, a locked store);
3 the store is damaged (``stores.errors.StoreCorruptionError``); 4 the store's disk is full; 5 the object
store holding it could not be reached (``StoreUnreachableError``); 130 interrupted.
"""
from __future__ import annotations

import argparse
import importlib
import sys

COMMANDS = {
    "render-frame": ("pipeline.cli_render", "render one frame of a generated scene to an .npz (+ PNG)"),
    "dataset": ("pipeline.cli_dataset", "build a dataset from a YAML config on a Dask cluster"),
    "validate": ("stores.validate", "check a store: schema, completeness, NaN/Inf, value ranges"),
    "export": ("pipeline.export", "export frames of a store to EXR, OIDN, layerdenoise or Noisebase layouts"),
    "estimate": ("pipeline.estimate", "predict samples, core-hours, store bytes and wall time of a config from a "
                 "short calibration render"),
    "bench": ("pipeline.bench", "benchmarks that print figures (renderer, store, scheduler, models)"),
}
EXIT_CODES_HELP = ("exit status: 0 ok; 1 problems found (validate) or frames failed (dataset); 2 bad input "
                   "(config, arguments, a path that is not a readable store, an unreachable cluster, a store "
                   "in use); 3 the store is damaged (missing or corrupt chunk files, array metadata that "
                   "disagrees with the schema); 4 a disk is full (the store's or an export's); 5 the store's "
                   "object store (S3 endpoint) "
                   "could not be reached: run again once it is back; 130 interrupted")


def main(argv: list[str] | None = None) -> int:
    """Run a command; its exit code. Ctrl-C anywhere, the chosen command's imports included, ends in one
    line and 130: ``interrupted``, with what stays when the command says (``__main__`` installs
    :mod:`core.interrupts` first)."""
    try:
        return _main(argv)
    except KeyboardInterrupt as e:            # e.g. pipeline.cli_dataset.DatasetInterrupted: what stays
        print(f"interrupted: {e}" if str(e) else "interrupted", file=sys.stderr)
        return 130


def _main(argv: list[str] | None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = argparse.ArgumentParser(prog="python -m pipeline", description=__doc__.splitlines()[0],
                                     epilog=EXIT_CODES_HELP)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    # Only the chosen sub-command's module is imported (mitsuba/torch imports are slow).
    chosen = next((a for a in argv if not a.startswith("-")), None)
    for name, (module, help_) in COMMANDS.items():
        p = sub.add_parser(name, help=help_, description=help_)
        if name == chosen:
            mod = importlib.import_module(module)
            mod.add_arguments(p)
            p.epilog = p.epilog or EXIT_CODES_HELP
            p.set_defaults(_run=mod.run)
    args = parser.parse_args(argv)
    from stores.objectstore import quiet_abandoned_requests, retry_defaults
    retry_defaults()
    quiet_abandoned_requests()
    from pipeline.errors import PipelineError
    from stores.errors import StoreCorruptionError, StoreError, exit_status, unreachable_exit
    from scene_gen.errors import SceneGenError
    from core.notices import plain_warnings
    try:
        with plain_warnings():                # a notice (frames left out, clips split, ...) is one plain line
            return int(args._run(args) or 0)
    except StoreCorruptionError as e:         # before StoreError: its message says damage (3, its exit_code)
        print(f"error: the store is damaged: {e}", file=sys.stderr)
        return exit_status(e)
    except (PipelineError, StoreError, SceneGenError) as e:
        print(f"error: {e}", file=sys.stderr)
        return exit_status(e)                 # 2, or the error's own: 4 a full disk, 5 an unreachable endpoint
    except Exception as e:                    # an s3:// store's endpoint is gone: 5; anything else is raised
        return unreachable_exit(e, getattr(args, "store", None) or getattr(args, "out", None),
                                getattr(args, "out", None))


if __name__ == "__main__":
    from core import interrupts
    interrupts.install()                # before the command's imports: Ctrl-C from here on ends in one line
    code = main()
    interrupts.stopping()               # done: a press during the exit (a cluster closing) does nothing
    sys.exit(code)
