"""Real processes for the cluster, kill and Ctrl-C tests: a ``dask scheduler`` started as a user would,
killing a process with everything it started, and a command pressed Ctrl-C at points it names itself."""
from __future__ import annotations

import os
import queue
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DASK = str(Path(sys.executable).parent / "dask")


def kill_group(proc: subprocess.Popen) -> None:
    """SIGKILL ``proc``'s process group (it was started with ``start_new_session=True``) and reap it."""
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    proc.wait(timeout=30)


def start_scheduler(scheduler_file: Path, env: dict, timeout: float = 60.0) -> subprocess.Popen:
    """``dask scheduler`` on 127.0.0.1 (any port, no dashboard), returned once its scheduler file exists."""
    proc = subprocess.Popen([DASK, "scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                             "--scheduler-file", str(scheduler_file)], env=env, cwd=ROOT, start_new_session=True,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    t0 = time.monotonic()
    while not scheduler_file.exists() and time.monotonic() - t0 < timeout:
        time.sleep(0.2)
    return proc


def python_m(package: str, hook: str = "") -> list[str]:
    """The command line of ``python -m PACKAGE`` (arguments to follow) that first runs ``hook``, Python code
    (e.g. a patch that prints a line on stdout and waits for one on stdin at a chosen point); the package
    then runs as ``-m`` runs it (runpy), its ``__main__`` block included."""
    if not hook:
        return [sys.executable, "-m", package]
    return [sys.executable, "-c", f"{hook}\nimport runpy\nrunpy.run_module({package!r}, run_name='__main__', "
                                  "alter_sys=True)"]


def pause_at(seam: str, flag: Path, seconds: float = 120.0) -> str:
    """Hook code for :func:`python_m`: the library's no-op seam ``seam`` (``"module:function"``, e.g.
    ``"pipeline.dataset:_commit_hook"``) replaced by one that, the first time it is reached, writes the
    process id to ``flag`` and sleeps ``seconds`` (a test kills the process there)."""
    module, name = seam.split(":")
    return (f"import importlib, os, time\n"
            f"def _pause(*args, **kwargs):\n"
            f"    if not os.path.exists({str(flag)!r}):\n"
            f"        with open({str(flag)!r}, 'w') as f:\n"
            f"            f.write(str(os.getpid()))\n"
            f"        time.sleep({seconds!r})\n"
            f"setattr(importlib.import_module({module!r}), {name!r}, _pause)")


def setting(target: str, value) -> str:
    """Hook code for :func:`python_m`: ``target`` (``"module:Class.ATTR"`` or ``"module:ATTR"``) set to ``value``."""
    module, attr = target.split(":")
    *owner, name = attr.split(".")
    obj = "m" + "".join(f".{o}" for o in owner)
    return f"import importlib\nm = importlib.import_module({module!r})\nsetattr({obj}, {name!r}, {value!r})"


class Command(subprocess.Popen):
    """A command started as a terminal starts it: in its own process group, so :meth:`ctrl_c` (SIGINT to the
    group) is a terminal's Ctrl-C and reaches the command's children too. Its stdout and stderr are read
    in threads (a full pipe never blocks it): :meth:`wait_for` a line it prints, :meth:`send` it a line."""

    def __init__(self, argv: list[str], env: dict | None = None):
        env = {**(os.environ if env is None else env), "PYTHONUNBUFFERED": "1"}      # its lines as it prints them
        super().__init__(argv, cwd=ROOT, env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, start_new_session=True)
        self.out, self.err, self._lines = [], [], queue.Queue()
        self._readers = [threading.Thread(target=self._read, args=(self.stdout, self.out, self._lines), daemon=True),
                         threading.Thread(target=self._read, args=(self.stderr, self.err, None), daemon=True)]
        for t in self._readers:
            t.start()

    @staticmethod
    def _read(stream, into: list, lines) -> None:
        for line in stream:
            into.append(line)
            if lines is not None:
                lines.put(line)

    def wait_for(self, text: str, timeout: float = 120.0) -> str:
        """The first line (from here on) of stdout that holds ``text``; AssertionError if the command ends
        or ``timeout`` passes first."""
        t0 = time.monotonic()
        while time.monotonic() - t0 < timeout:
            try:
                line = self._lines.get(timeout=0.2)
            except queue.Empty:
                if self.poll() is not None and not self._readers[0].is_alive() and self._lines.empty():
                    raise AssertionError(f"ended ({self.returncode}) before printing {text!r}: "
                                         f"{''.join(self.err)[-3000:]}") from None
                continue
            if text in line:
                return line
        raise AssertionError(f"no line with {text!r} within {timeout} s: {''.join(self.out)[-2000:]}")

    def ctrl_c(self, presses: int = 1, gap: float = 0.1) -> None:
        """Ctrl-C ``presses`` times, ``gap`` seconds apart (SIGINT to the process group)."""
        for i in range(presses):
            if i:
                time.sleep(gap)
            try:
                os.killpg(self.pid, signal.SIGINT)
            except ProcessLookupError:
                return

    def ctrl_c_when(self, ready, presses: int = 5, poll: float = 0.1, timeout: float = 60.0) -> None:
        """Ctrl-C ``presses`` times once ``ready()`` holds (or after ``timeout`` s, or once the command has
        ended), polling every ``poll`` s; on any error the whole process group is killed first."""
        try:
            t0 = time.monotonic()
            while time.monotonic() - t0 < timeout and self.poll() is None and not ready():
                time.sleep(poll)
            self.ctrl_c(presses=presses)
        except BaseException:
            kill_group(self)
            raise

    def send(self, line: str = "") -> None:
        """A line on the command's stdin (nothing if it has closed it)."""
        try:
            self.stdin.write(line + "\n")
            self.stdin.flush()
        except (BrokenPipeError, ValueError):
            pass

    def finish(self, timeout: float = 60.0) -> tuple[int, str, str]:
        """The exit code, stdout and stderr once the command ends (killed with its group after ``timeout``)."""
        try:
            self.wait(timeout=timeout)
        finally:
            if self.poll() is None:
                kill_group(self)
            try:
                self.stdin.close()
            except BrokenPipeError:
                pass
        for t in self._readers:
            t.join(timeout=10)
        return self.returncode, "".join(self.out), "".join(self.err)


def last_line(err: str, line: str) -> None:
    """``err`` (a command's stderr) ends with exactly ``line``, the only line that says ``interrupted``, and
    holds no traceback and no "Exception ignored" (nothing after the one line)."""
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert lines and lines[-1] == line, err[-3000:]
    assert [ln for ln in lines if "interrupted" in ln] == [line], err[-3000:]
    assert "Traceback" not in err and "Exception ignored" not in err and "leaked" not in err, err[-3000:]
