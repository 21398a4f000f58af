"""``python -m stores COMMAND`` (see ``--help``): the commands of :mod:`stores.commands`, run through
:func:`core.cli.run_main` (one exit-code table, one line for each error)."""
from core.cli import run_main, start


def main(argv: list[str] | None = None) -> int:
    from stores.commands import PROGRAM
    return run_main(PROGRAM, argv)


if __name__ == "__main__":
    start(main)
