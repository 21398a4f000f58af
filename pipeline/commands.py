"""The commands of ``python -m pipeline``: render-frame, dataset, validate, export, estimate, bench.

Each lives in its own module with ``add_arguments(parser)`` and ``run(args) -> int``; only the chosen
one's module is imported. Errors, exit codes and Ctrl-C are :func:`core.cli.run_main`'s, the same for
every command.
"""
from __future__ import annotations

from core.cli import Program, lazy_parser
from stores.commands import explain, setup

COMMANDS = {
    "render-frame": ("pipeline.cli_render", "render one frame of a generated scene to an .npz (+ PNG)"),
    "dataset": ("pipeline.cli_dataset", "build a dataset from a YAML config on a Dask cluster"),
    "validate": ("stores.validate", "check a store: schema, completeness, NaN/Inf, value ranges"),
    "export": ("pipeline.export", "export frames of a store to EXR, OIDN, layerdenoise or Noisebase layouts"),
    "estimate": ("pipeline.estimate", "predict samples, core-hours, store bytes and wall time of a config from a "
                 "short calibration render"),
    "bench": ("pipeline.bench", "benchmarks that print figures (renderer, store, scheduler, models)"),
}
PROGRAM = Program(parser=lazy_parser("python -m pipeline", __doc__.splitlines()[0], COMMANDS), setup=setup,
                  explain=explain)
