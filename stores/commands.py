"""The commands of ``python -m stores``: validate, export, bench, upgrade (``python -m pipeline validate|export``
run the same functions; its export adds the formats of packages above, such as ``noisebase``), and the
set-up and error translation every command that reads or writes stores shares (:mod:`core.cli`)."""
from __future__ import annotations

from core.cli import Program, lazy_parser

COMMANDS = {
    "validate": ("stores.validate", "check a store: schema, completeness, NaN/Inf, value ranges"),
    "export": ("stores.export", "export frames of a store to EXR, OIDN, layerdenoise or an installed format"),
    "bench": ("stores.cli_bench", "crop-read benchmark of a store or synthetic frames (figures printed)"),
    "upgrade": ("stores.upgrade.migrate", "turn a store of an older schema version into the current one (in place, resumable)"),
}


def setup(args) -> None:
    """``Program.setup`` of a command that touches stores: botocore's retries for s3:// stores, and the
    requests a failed connection leaves pending are dropped quietly at exit."""
    from stores.objectstore import quiet_abandoned_requests, retry_defaults
    retry_defaults()
    quiet_abandoned_requests()


def explain(e: BaseException, args):
    """``Program.explain`` of a command that touches stores: a failed connection to an s3:// store's
    endpoint is that store's one-line error (exit 5)."""
    from stores.errors import explain as store_error
    return store_error(e, getattr(args, "store", None) or getattr(args, "out", None))


PROGRAM = Program(parser=lazy_parser("python -m stores", __doc__.splitlines()[0], COMMANDS), setup=setup,
                  explain=explain)
