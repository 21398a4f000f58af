"""Files written whole or not at all: through a temporary file beside the target and a rename, so a
reader never sees half a file and an interrupted write leaves the old one."""
from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Callable, IO


def new_file_mode() -> int:
    """The permissions ``open(path, "w")`` gives a new file here: 0o666 less the process's umask (read
    from /proc where it can be, since setting the umask to learn it is not thread-safe)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return 0o666 & ~int(line.split()[1], 8)
    except OSError:
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return 0o666 & ~mask


def temp_name_pattern(path) -> str:
    """The glob of the temporary files :func:`write_atomically` makes beside ``path``."""
    return f".{Path(path).name}-*.tmp"


def remove_stale_temps(path) -> list[Path]:
    """Delete what a write of ``path`` cut short by a SIGKILL left (:func:`write_atomically`'s temporary
    files beside it; its ``finally`` never ran). Call it only where no other process writes ``path``."""
    path = Path(path)
    gone = sorted(path.parent.glob(temp_name_pattern(path))) if path.parent.is_dir() else []
    for p in gone:
        p.unlink(missing_ok=True)
    return gone


def write_atomically(path, write: Callable[[IO], None], binary: bool = False) -> Path:
    """``write(f)`` into a temporary file beside ``path``, then rename it to ``path``, with the
    permissions of any other new file (``tempfile.mkstemp`` makes its files 0600: a JSON or a checkpoint
    that others may read should not be). The folder must exist."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}-", suffix=".tmp", dir=path.parent)
    try:
        os.fchmod(fd, new_file_mode())
        with os.fdopen(fd, "wb" if binary else "w") as f:
            write(f)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path
