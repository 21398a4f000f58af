"""One way out of every command line: ``python -m pipeline``, ``stores``, ``training``, ``studies``,
``scene_gen`` and ``training.checkpoint`` each describe their commands as a :class:`Program` and run them
through :func:`run_main`, which parses, runs, and turns what went wrong into one line on stderr and an
exit code of the one table, :data:`EXIT_CODES` (printed under every ``--help`` as :data:`EXIT_CODES_HELP`).

An error tells its own code (``exit_code``: 1 a training loss that became NaN, 3 damage, 4 a full disk,
5 an unreachable object store); any other error of the project is bad input (2). A full disk anywhere
in an error's chain (``ENOSPC``, ``EDQUOT``) is 4 whichever command met it. An error from a library below
(botocore's failed connection) becomes the project's through the program's ``explain``; anything else is
a bug and is raised, traceback and all. Ctrl-C is one line, ``interrupted: WHAT STAYS``, and 130.

Light on purpose: a ``__main__`` imports it before :func:`core.interrupts.install` (so before torch).
"""
from __future__ import annotations

import argparse
import sys
import importlib
from dataclasses import dataclass
from typing import Callable

from core.errors import DISK_FULL_HINT, ProjectError, disk_full, is_disk_full

OK, PROBLEMS, BAD_INPUT, DAMAGED, DISK_FULL, UNREACHABLE, INTERRUPTED = 0, 1, 2, 3, 4, 5, 130
EXIT_CODES = {
    OK: "done",
    PROBLEMS: "problems found (validate, hard-cases), frames that failed (dataset), or a training run whose "
              "loss became NaN/Inf",
    BAD_INPUT: "bad input: a config, an argument or a setting, a path that is not a readable store, a split or "
               "checkpoint that cannot be used as asked (frames validate flags included: --skip-bad-frames "
               "leaves them out), an unreachable or wrong cluster, a store in use",
    DAMAGED: "the store is damaged (a complete frame's file missing or corrupt, array metadata that disagrees "
             "with the schema; see python -m pipeline validate)",
    DISK_FULL: "a disk is full (the store's, or that of a checkpoint, evaluation, report, export or scene file "
               "being written): free space and run again",
    UNREACHABLE: "the S3 endpoint of an s3:// store could not be reached: run again once it is back",
    INTERRUPTED: "interrupted (Ctrl-C: one line says what stays; the same command resumes)",
}
EXIT_CODES_HELP = "exit status: " + "; ".join(f"{code} {text}" for code, text in EXIT_CODES.items())


@dataclass(frozen=True)
class Program:
    """What :func:`run_main` needs of a command-line program. ``parser(argv)`` builds its parser (it may
    import only the command ``argv`` names; a :class:`ProjectError` it raises is the answer, as a moved
    command's); each parsed command carries ``run(args) -> int`` (``set_defaults(run=...)``). The
    optional hooks: ``setup(args)`` before the command runs; ``explain(error, args)``, an error from a
    library below as the project's (or None); ``interrupted(error, args, argv)``, what stays after
    Ctrl-C (``args`` None before parsing; default: the interrupt's own text); ``again(args)``, what to do
    after a full disk (default: :data:`core.errors.DISK_FULL_HINT`); ``bad_input``, library errors that
    are bad input (exit 2, one line)."""
    parser: Callable[[list[str]], argparse.ArgumentParser]
    setup: Callable[[argparse.Namespace], None] | None = None
    explain: Callable[[BaseException, argparse.Namespace | None], BaseException | None] | None = None
    interrupted: Callable[[KeyboardInterrupt, argparse.Namespace | None, list[str]], str] | None = None
    again: Callable[[argparse.Namespace | None], str | None] | None = None
    bad_input: tuple[type[BaseException], ...] = ()


def program_parser(prog: str, description: str) -> argparse.ArgumentParser:
    """A program's parser, the exit-code table under its ``--help``."""
    return argparse.ArgumentParser(prog=prog, description=description, epilog=EXIT_CODES_HELP)


def commands(parser: argparse.ArgumentParser, dest: str = "command"):
    """``parser``'s sub-commands (required); each parser they add has the exit-code table under its help."""
    sub = parser.add_subparsers(dest=dest, metavar="COMMAND", required=True)
    add = sub.add_parser

    def add_parser(name, **kw):
        kw.setdefault("epilog", EXIT_CODES_HELP)
        kw.setdefault("description", kw.get("help"))
        return add(name, **kw)
    sub.add_parser = add_parser
    return sub


def lazy_parser(prog: str, description: str, table: dict[str, tuple[str, str]]):
    """``Program.parser`` for a program whose commands each live in a module of ``table`` (name -> (module,
    help)) with ``add_arguments(parser)`` and ``run(args)``: every command is listed, and only the module of
    the one ``argv`` names is imported (mitsuba and torch imports are slow)."""
    def parser(argv: list[str]) -> argparse.ArgumentParser:
        p = program_parser(prog, description)
        sub = commands(p)
        chosen = next((a for a in argv if not a.startswith("-")), None)
        for name, (module, help_) in table.items():
            s = sub.add_parser(name, help=help_)
            if name == chosen:
                mod = importlib.import_module(module)
                mod.add_arguments(s)
                s.set_defaults(run=mod.run)
        return p
    return parser


def exit_code(err: BaseException) -> int:
    """The exit code for ``err``: the ``exit_code`` of it or of an error it was raised from, else 4 for a
    full disk anywhere in its chain, else 2."""
    seen, e = set(), err
    while e is not None and id(e) not in seen:
        seen.add(id(e))
        code = getattr(e, "exit_code", None)
        if isinstance(code, int):
            return code
        e = e.__cause__
    return DISK_FULL if is_disk_full(err) else BAD_INPUT


def message(err: BaseException) -> str:
    """The one line for ``err``: the ``lead`` of it or of an error it was raised from (a damaged store's "the
    store is damaged: ") and its text; for
    an error re-raised from a DataLoader worker (whose text carries the worker's traceback), the original
    error's text from that traceback's last line."""
    text = str(err)
    if "Original Traceback" in text:
        last = [ln for ln in text.splitlines() if ln.strip()][-1]
        text = last.split(": ", 1)[1] if ": " in last else last
    seen, e, lead = set(), err, ""
    while e is not None and id(e) not in seen and not lead:     # the lead of it or of what it was raised from
        seen.add(id(e))
        lead, e = getattr(e, "lead", ""), e.__cause__
    return lead + text


def run_main(program: Program, argv: list[str] | None = None) -> int:
    """Run the command ``argv`` (default: ``sys.argv[1:]``) of ``program``; its exit code. A warning of the
    project prints as one plain line (:func:`core.notices.plain_warnings`)."""
    from core.notices import plain_warnings
    argv = list(sys.argv[1:] if argv is None else argv)
    args = None
    try:
        try:
            args = program.parser(argv).parse_args(argv)
            if program.setup is not None:
                program.setup(args)
            with plain_warnings():
                return int(args.run(args) or 0)
        except KeyboardInterrupt:
            raise
        except Exception as e:  # noqa: BLE001 - each one is judged below, and raised again if not ours
            return _fail(program, e, args)
    except KeyboardInterrupt as e:
        kept = program.interrupted(e, args, argv) if program.interrupted is not None else str(e)
        print(f"interrupted: {kept}" if kept else "interrupted", file=sys.stderr)
        return INTERRUPTED


def _fail(program: Program, e: Exception, args) -> int:
    """One line on stderr for ``e`` and its exit code; ``e`` raised again when it is no error of ours."""
    err = (program.explain(e, args) if program.explain is not None else None) or e
    if not isinstance(err, ProjectError):
        if is_disk_full(err):
            again = program.again(args) if program.again is not None else None
            err = disk_full(err, getattr(args, "out", None), again or DISK_FULL_HINT)
        elif not isinstance(err, program.bad_input):
            raise e
    print(f"error: {message(err)}", file=sys.stderr)
    return exit_code(err)


def start(main: Callable[[], int], then: Callable[[int], None] | None = None) -> None:
    """A ``__main__``'s whole body: Ctrl-C from here on ends in one line (:mod:`core.interrupts`, before the
    command's heavy imports), run ``main``, ignore Ctrl-C during the exit (a cluster closing), ``then(code)``
    and exit with the code."""
    from core import interrupts
    interrupts.install()
    code = main()
    interrupts.stopping()
    if then is not None:
        then(code)
    sys.exit(code)
