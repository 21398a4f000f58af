"""This process and others on this host, as a store records them: who creates a store
(``stores.create.create_store``'s ``creating`` attribute) and who holds its writer lock
(``stores.lock``). A record is the host, the pid, the process's start time (``proc_start``, clock
ticks since boot, :func:`process_start`: it tells a process from a later one that reused its pid) and the wall-clock start;
:func:`pid_alive` says whether the process a record of this host names still runs.
"""
from __future__ import annotations

import os
import socket
import time


def holder_record(**extra) -> dict:
    """This process as a store records it: ``host``, ``pid``, ``proc_start``, ``started`` (UTC), then ``extra``."""
    return {"host": socket.gethostname(), "pid": os.getpid(), "proc_start": process_start(os.getpid()),
            "started": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), **extra}


def _proc_stat(pid: int) -> list[str] | None:
    """The fields of ``/proc/<pid>/stat`` after "pid (comm)" (the state is the first), None if unknown."""
    try:
        with open(f"/proc/{int(pid)}/stat") as f:
            text = f.read()
    except OSError:
        return None
    return text[text.rindex(")") + 2:].split()


def process_start(pid: int) -> int | None:
    """Start time of ``pid`` in clock ticks since boot (``/proc/<pid>/stat`` field 22), None if unknown."""
    rest = _proc_stat(pid)
    try:
        return int(rest[19]) if rest else None
    except (IndexError, ValueError):
        return None


def _proc_state(pid: int) -> str | None:
    rest = _proc_stat(pid)
    return rest[0] if rest else None


def pid_alive(pid: int, proc_start: int | None = None) -> bool:
    """Whether process ``pid`` runs on this host (not a zombie, and, given its recorded ``proc_start``
    (:func:`process_start`), the same process rather than a later one that reused the pid). ``pid <= 0``
    is never a process (``os.kill(0 or -1, 0)`` would signal a process group or every process)."""
    try:
        if int(pid) <= 0:
            return False
        os.kill(int(pid), 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass                            # exists, owned by someone else
    except (OverflowError, ValueError, TypeError):
        return False
    if _proc_state(pid) == "Z":
        return False
    if proc_start is not None:
        now = process_start(pid)
        if now is not None and now != int(proc_start):
            return False
    return True
