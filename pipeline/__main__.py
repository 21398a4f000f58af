"""``python -m pipeline COMMAND``: render-frame, dataset, validate, export, bench.

Each sub-command lives in its own module with ``add_arguments(parser)`` and ``run(args) -> int``;
this file only dispatches and turns library errors into one-line messages and exit codes.
"""
from __future__ import annotations

import argparse
import importlib
import sys

COMMANDS = {
    "render-frame": ("pipeline.cli_render", "render one frame of a generated scene to an .npz (+ PNG)"),
    "dataset": ("pipeline.cli_dataset", "build a dataset from a YAML config on a Dask cluster"),
    "validate": ("stores.validate", "check a store: schema, completeness, NaN/Inf, value ranges"),
    "export": ("stores.export", "export frames of a store to EXR, OIDN or layerdenoise layouts"),
    "bench": ("pipeline.bench", "benchmarks that print figures (renderer, store, scheduler, models)"),
}


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = argparse.ArgumentParser(prog="python -m pipeline", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    # Only the chosen sub-command's module is imported (mitsuba/torch imports are slow).
    chosen = next((a for a in argv if not a.startswith("-")), None)
    for name, (module, help_) in COMMANDS.items():
        p = sub.add_parser(name, help=help_, description=help_)
        if name == chosen:
            mod = importlib.import_module(module)
            mod.add_arguments(p)
            p.set_defaults(_run=mod.run)
    args = parser.parse_args(argv)
    from pipeline.errors import PipelineError
    try:
        from stores.errors import StoreError
    except ImportError:  # pragma: no cover
        StoreError = PipelineError
    from scene_gen.errors import SceneGenError
    try:
        return int(args._run(args) or 0)
    except (PipelineError, StoreError, SceneGenError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
