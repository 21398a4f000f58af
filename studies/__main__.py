"""``python -m studies scaling|bench-scale`` (see ``--help`` of each): the commands of
:mod:`studies.commands`, run through :func:`core.cli.run_main` (one exit-code table, one line for each error)."""
from core.cli import run_main, start


def main(argv: list[str] | None = None) -> int:
    from studies.commands import PROGRAM
    return run_main(PROGRAM, argv)


if __name__ == "__main__":
    start(main)
