"""Real processes for the cluster and kill tests: a ``dask scheduler`` started as a user would, and
killing a process with everything it started."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
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
