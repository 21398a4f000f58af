"""One way out of every command (``core.cli``): every program and every command prints the one exit-code
table under its ``--help``, and one failure of each kind, each through a different program, ends in one
``error:`` (or ``interrupted``) line on stderr and the code the table gives that kind."""
from __future__ import annotations

import ast
import os
import subprocess
import sys
from pathlib import Path

import pytest

from procs import Command, kill_group, python_m

ROOT = Path(__file__).resolve().parent.parent
PROGRAMS = ("pipeline", "stores", "training", "studies", "scene_gen", "training.checkpoint")


def _env(**extra) -> dict:
    return {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""), **extra}


def _run(*argv: str, **env) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", *argv], env=_env(**env), cwd=ROOT, capture_output=True, text=True,
                          timeout=300)


def _one_line(r: subprocess.CompletedProcess, start: str = "error: ") -> str:
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith(start), r.stderr[-3000:]
    return lines[0]


def _words(text: str) -> str:
    return " ".join(text.split())


def _command_names(program: str) -> list[str]:
    """The commands of ``python -m PROGRAM`` (its parser's sub-command choices)."""
    import importlib
    parser = (importlib.import_module("training.checkpoint")._parser([]) if program == "training.checkpoint"
              else importlib.import_module(f"{program}.commands").PROGRAM.parser([]))
    sub = next(a for a in parser._actions if isinstance(a.choices, dict))
    return list(sub.choices)


def test_the_exit_code_table_exists_once_and_names_every_kind():
    from core.cli import EXIT_CODES, EXIT_CODES_HELP
    assert set(EXIT_CODES) == {0, 1, 2, 3, 4, 5, 130}
    for code, text in EXIT_CODES.items():
        assert f"{code} {text}" in EXIT_CODES_HELP
    found = []                                  # no second table: no other module spells the codes out
    for pkg in ("core", "scene_gen", "stores", "pipeline", "training", "studies"):
        for p in (ROOT / pkg).rglob("*.py"):
            if p == ROOT / "core" / "cli.py":
                continue
            for node in ast.walk(ast.parse(p.read_text())):
                if isinstance(node, ast.Constant) and isinstance(node.value, str) and (
                        "exit status:" in node.value or "exit codes:" in node.value):
                    found.append(str(p.relative_to(ROOT)))
    assert not found, found


@pytest.mark.parametrize("program", PROGRAMS)
def test_every_command_prints_the_table_under_its_help(program):
    from core.cli import EXIT_CODES_HELP
    table = _words(EXIT_CODES_HELP)
    r = _run(program, "--help")
    assert r.returncode == 0 and table in _words(r.stdout), r.stdout + r.stderr
    for name in _command_names(program):
        r = _run(program, name, "--help")
        assert r.returncode == 0 and table in _words(r.stdout), f"{program} {name}: {r.stdout[-2000:]}{r.stderr}"


def test_every_main_is_a_few_lines():
    """Each ``__main__.py`` is the program's name and ``core.cli.start``: at most 15 lines of code."""
    for p in ROOT.glob("*/__main__.py"):
        code = [ln for ln in ast.unparse(ast.parse(p.read_text())).splitlines() if ln.strip()]
        body = [ln for ln in code if not ln.lstrip().startswith(('"""', "'"))]
        assert len(body) <= 15, f"{p.relative_to(ROOT)}: {len(body)} lines of code"


def test_bad_input_is_2():
    from core.cli import BAD_INPUT
    r = _run("pipeline", "dataset", "--config", "configs/no-such.yaml", "--out", "/tmp/never.zarr")
    assert r.returncode == BAD_INPUT and "configs/no-such.yaml" in _one_line(r)
    r = _run("scene_gen", "spec", "--res", "0")
    assert r.returncode == BAD_INPUT and "--res must be >= 1" in _one_line(r)
    r = _run("training", "scaling")                 # a command that moved: one line naming where it is
    assert r.returncode == BAD_INPUT and "python -m studies scaling" in _one_line(r)


def test_problems_found_is_1_and_damage_is_3(tmp_path):
    import zarr

    from core.cli import DAMAGED, PROBLEMS
    from stores.reader import open_store
    from test_stores_faults import _shard
    from test_training import make_store
    store = make_store(tmp_path / "s.zarr", h=8, w=8, spp=2, per_split=(1, 1, 1))
    train = open_store(store).frames_in_split("train")[0]
    zarr.open_group(str(store), mode="r+")["status/complete"][train] = False      # one frame left incomplete
    r = _run("stores", "validate", str(store))
    assert r.returncode == PROBLEMS, r.stdout[-2000:] + r.stderr
    os.remove(_shard(store, "reference/radiance", open_store(store).frames_in_split("test")[0]))   # one lost
    r = _run("training", "evaluate", "--checkpoint", "input", "--store", str(store), "--out",
             str(tmp_path / "e.json"), "--no-flip")
    assert r.returncode == DAMAGED and _one_line(r).startswith("error: the store is damaged: "), r.stderr


@pytest.fixture
def full_disk(small_disk):
    """The 1 MiB tmpfs of ``small_disk`` (conftest), filled up."""
    st = os.statvfs(small_disk)
    (small_disk / "filler").write_bytes(b"\0" * (st.f_bavail * st.f_frsize))
    return small_disk


def test_a_full_disk_is_4_in_scene_gen_too(full_disk):
    """scene_gen once answered every OSError with 2; a full disk is 4 there as in every command."""
    from core.cli import DISK_FULL
    r = _run("scene_gen", "real-scenes", "--out", str(full_disk / "scenes"))
    line = _one_line(r)
    assert r.returncode == DISK_FULL and "no space left on the device" in line and str(full_disk) in line, r.stderr


def test_an_unreachable_object_store_is_5():
    pytest.importorskip("s3fs")
    import socket
    from core.cli import UNREACHABLE
    with socket.socket() as s:                      # a port nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    r = _run("pipeline", "validate", "s3://no-bucket/s.zarr", AWS_ENDPOINT_URL=f"http://127.0.0.1:{port}",
             AWS_ACCESS_KEY_ID="x", AWS_SECRET_ACCESS_KEY="x", AWS_MAX_ATTEMPTS="1")
    line = _one_line(r)
    assert r.returncode == UNREACHABLE and "could not be reached" in line and str(port) in line, r.stderr


def test_ctrl_c_is_130_in_one_line():
    from core.cli import INTERRUPTED
    hook = ("import scene_gen.commands as c, time\n"
            "def wait(a):\n    print('ready', flush=True)\n    time.sleep(60)\n"
            "c._spec = wait\n")
    proc = Command(python_m("scene_gen", hook) + ["spec"], env=_env())
    try:
        proc.wait_for("ready")
        proc.ctrl_c()
        proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            kill_group(proc)
    assert proc.returncode == INTERRUPTED and "".join(proc.err).strip() == "interrupted", proc.err


def test_a_press_while_held_back_takes_effect_when_the_block_ends():
    """``core.interrupts.held_back`` (a pool's workers being spawned): a Ctrl-C meanwhile, taken by another
    thread, raises only once the block ends. Raised in its middle, it left a half-spawned worker that
    printed an ``EOFError`` traceback after the command's one line."""
    import signal
    import threading
    import time

    from core import interrupts
    reached = []
    with pytest.raises(KeyboardInterrupt):
        with interrupts.held_back():
            t = threading.Thread(target=os.kill, args=(os.getpid(), signal.SIGINT))
            t.start()
            t.join()
            for _ in range(50):
                time.sleep(0.002)           # bytecode boundaries: a handler would run here
            reached.append(True)
    assert reached == [True] and signal.getsignal(signal.SIGINT) is signal.default_int_handler


_GC_PRESS = r'''
import gc, os, signal, sys, time
from core import interrupts
interrupts.install()
sent = []
def during_a_collection(phase, info):        # distributed registers such a callback (its GC diagnosis)
    if phase == "start" and not sent:
        sent.append(os.kill(os.getpid(), signal.SIGINT))
        t = time.monotonic()
        while time.monotonic() - t < 0.05:  # the handler runs here, inside the callback
            pass
gc.callbacks.append(during_a_collection)
try:
    gc.collect()
    t = time.monotonic()
    while time.monotonic() - t < 3:
        time.sleep(0.01)
    print("not interrupted")
except KeyboardInterrupt:
    print("interrupted")
'''


def test_a_press_that_lands_in_a_garbage_collector_callback_is_not_lost():
    """A first Ctrl-C whose handler ran inside a gc callback raised KeyboardInterrupt where Python swallows
    it ("Exception ignored in ..."), and later presses were ignored: a dataset run pressed five times ran to
    its end (exit 0). The press is delivered again once the callback is over."""
    r = subprocess.run([sys.executable, "-c", _GC_PRESS], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert r.stdout.strip() == "interrupted" and "Exception ignored" not in r.stderr, r.stdout + r.stderr
