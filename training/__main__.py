"""``python -m training COMMAND`` (see ``--help``): the commands of :mod:`training.commands`, run through
:func:`core.cli.run_main` (one exit-code table, one line for each error)."""
import sys

from core.cli import run_main, start


def main(argv: list[str] | None = None) -> int:
    from training.commands import PROGRAM
    return run_main(PROGRAM, argv)


def _end(code: int) -> None:
    dist = sys.modules.get("training.distributed")      # under torchrun every rank leaves through it
    if dist is not None:
        dist.end_process(code)


if __name__ == "__main__":
    start(main, then=_end)
