"""``python -m scene_gen preview|spec|contact-sheet|real-scenes`` (see ``--help``): the commands of
:mod:`scene_gen.commands`, run through :func:`core.cli.run_main` (one exit-code table, one line for each
error)."""
from core.cli import run_main, start
from scene_gen.commands import PROGRAM


def main(argv: list[str] | None = None) -> int:
    return run_main(PROGRAM, argv)


if __name__ == "__main__":
    start(main)
