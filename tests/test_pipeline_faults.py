"""``python -m pipeline dataset`` under a hostile but fair user: bounded waits, one-line errors, no data lost.

Real processes and real servers: a scheduler address where an HTTP server listens, SIGINT to the
LocalCluster's worker processes mid-run, a store on a file system that fills up (a tmpfs mounted by the
test, as root), ``--overwrite`` on a symbolic link, two runs taking one store's lock at once.
"""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from procs import kill_group
from test_pipeline_safety import _env

ROOT = Path(__file__).resolve().parent.parent
SMOKE = ROOT / "configs" / "smoke.yaml"
PY = sys.executable


def _dataset(out, *extra, config=SMOKE, timeout=600) -> subprocess.CompletedProcess:
    return subprocess.run([PY, "-m", "pipeline", "dataset", "--config", str(config), "--out", str(out),
                           "--no-progress", *extra], env=_env(), cwd=ROOT, capture_output=True, text=True,
                          timeout=timeout)


def _one_line_error(r: subprocess.CompletedProcess) -> str:
    """The run's stderr, asserted to be a single ``error: ...`` line (no traceback)."""
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and "Traceback" not in r.stderr, r.stderr[-3000:]
    return lines[0]


# ---- 7, 10: addresses that are not a scheduler or a dashboard --------------------------------------
@pytest.fixture()
def http_server():
    """A plain HTTP server on 127.0.0.1 (what a mistyped scheduler port may reach)."""
    from http.server import HTTPServer, SimpleHTTPRequestHandler
    srv = HTTPServer(("127.0.0.1", 0), SimpleHTTPRequestHandler)
    t = threading.Thread(target=srv.serve_forever, daemon=True)
    t.start()
    yield srv.server_address[1]
    srv.shutdown()


def test_a_scheduler_address_where_an_http_server_listens_fails_within_the_timeout(tmp_path, http_server):
    t0 = time.monotonic()
    r = _dataset(tmp_path / "s.zarr", "--scheduler", f"tcp://127.0.0.1:{http_server}", timeout=120)
    took = time.monotonic() - t0
    assert r.returncode == 2
    line = _one_line_error(r)
    assert f"tcp://127.0.0.1:{http_server} accepts connections but does not answer as a Dask scheduler" in line
    assert took < 10 + 1 + 30                    # connect_timeout (10 s) + 1 s, and the imports


@pytest.mark.parametrize("address", ["notaurl", "tcp://host:notaport", "tcp://:8786", "foo://host:1"])
def test_a_scheduler_that_is_not_an_address_is_a_config_error(tmp_path, address, capsys):
    from pipeline.__main__ import main
    rc = main(["dataset", "--config", str(SMOKE), "--out", str(tmp_path / "s.zarr"), "--scheduler", address])
    err = capsys.readouterr().err
    assert rc == 2 and f"--scheduler {address!r} is not a scheduler address" in err, err
    assert len(err.strip().splitlines()) == 1 and not (tmp_path / "s.zarr").exists()


@pytest.mark.parametrize("address, message", [
    ("foo", "must be host:port (or :port) with a port in 0..65535"),
    ("127.0.0.1:99999", "must be host:port (or :port) with a port in 0..65535"),
    ("10.255.255.1:8787", "cannot be served on this machine (Cannot assign requested address)"),
    ("nosuchhost.invalid:8787", "cannot be served on this machine"),
])
def test_a_bad_dashboard_address_is_a_one_line_config_error(tmp_path, address, message):
    d = yaml.safe_load(SMOKE.read_text())
    d["cluster"]["dashboard_address"] = address
    cfg = tmp_path / "dash.yaml"
    cfg.write_text(yaml.safe_dump(d))
    r = _dataset(tmp_path / "s.zarr", config=cfg, timeout=120)
    assert r.returncode == 2
    line = _one_line_error(r)
    assert "dataset.cluster.dashboard_address" in line and message in line, line
    assert not (tmp_path / "s.zarr").exists()


def test_too_many_local_workers_is_a_config_error_that_names_workers(tmp_path, capsys):
    from pipeline.__main__ import main
    for n in ("100000", "4000"):
        rc = main(["dataset", "--config", str(SMOKE), "--out", str(tmp_path / "s.zarr"), "--workers", n])
        err = capsys.readouterr().err
        assert rc == 2 and "--workers" in err and "resolution" not in err, err


# ---- 11: --overwrite never deletes through a link -----------------------------------------------------
def test_overwrite_on_a_symbolic_link_deletes_nothing(tmp_path, capsys):
    from pipeline.__main__ import main
    target = tmp_path / "home"
    (target / "sub").mkdir(parents=True)
    (target / "thesis.tex").write_text("years of work")
    (target / "sub" / "data.bin").write_bytes(b"\1" * 64)
    link = tmp_path / "data.zarr"
    link.symlink_to(target)
    rc = main(["dataset", "--config", str(SMOKE), "--out", str(link), "--overwrite"])
    err = capsys.readouterr().err
    assert rc == 2 and "is a symbolic link to" in err and "never deletes through a link" in err, err
    assert (target / "thesis.tex").read_text() == "years of work" and (target / "sub" / "data.bin").exists()
    from stores import create
    from stores.errors import ForeignStoreError
    with pytest.raises(ForeignStoreError, match="never deletes through a link"):
        create._clear(link)
    assert (target / "thesis.tex").exists()


# ---- smaller: two runs taking a store's lock in the same instant ------------------------------------
def test_a_lock_taken_in_the_same_instant_names_its_holder(tmp_path):
    """The second of two runs that start together meets the first's lock before its record is written:
    it waits for the record instead of reporting 'pid None on host None'."""
    import fcntl
    import json
    import socket
    from stores.errors import StoreLockedError
    from stores.lock import StoreLock
    store = tmp_path / "s.zarr"
    store.mkdir()
    fd = os.open(store / "dataset.lock", os.O_RDWR | os.O_CREAT)
    fcntl.flock(fd, fcntl.LOCK_EX)                   # run A holds the lock, its record not yet written

    def write_record():
        time.sleep(0.5)
        os.pwrite(fd, json.dumps({"host": socket.gethostname(), "pid": 4242, "started": "now"}).encode(), 0)
    threading.Thread(target=write_record).start()
    try:
        with pytest.raises(StoreLockedError) as e:
            StoreLock(store).acquire()
        assert "pid 4242 on host" in str(e.value) and "None" not in str(e.value)
        os.ftruncate(fd, 0)                           # a holder that never writes: said so, no "None"
        with pytest.raises(StoreLockedError, match="started at the same moment") as e:
            StoreLock(store).acquire()
        assert "pid None" not in str(e.value)
    finally:
        os.close(fd)


# ---- 8: SIGINT to the local worker processes ------------------------------------------------------
def _worker_pids(pid: int) -> list[int]:
    """The LocalCluster worker processes under ``pid`` (multiprocessing's spawned children)."""
    out = subprocess.run(["ps", "-ww", "-eo", "pid,ppid,args"], capture_output=True, text=True).stdout
    return [int(ln.split()[0]) for ln in out.splitlines()[1:]
            if ln.split()[1] == str(pid) and "spawn_main" in ln]


def test_sigint_to_the_local_workers_neither_kills_them_nor_stores_a_cut_render(tmp_path):
    """A Ctrl-C that reaches the worker processes (not the client) used to close them for good and leave
    the run waiting forever. Now the workers leave SIGINT to the client; a render that Mitsuba's own
    SIGINT handler cut short is not stored (the task fails and is retried). The run finishes and its
    store equals a run without signals, array for array."""
    import zarr
    out = tmp_path / "s.zarr"
    proc = subprocess.Popen([PY, "-m", "pipeline", "dataset", "--config", str(SMOKE), "--out", str(out),
                             "--no-progress"], env=_env(), cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, start_new_session=True)
    sent = 0
    try:
        t0 = time.monotonic()
        while proc.poll() is None and time.monotonic() - t0 < 300:
            pids = _worker_pids(proc.pid)
            if pids and (out / "zarr.json").exists() and sent < 3:
                for p in pids:
                    try:
                        os.kill(p, signal.SIGINT)
                    except ProcessLookupError:
                        pass
                sent += 1
                time.sleep(1.5)
            time.sleep(0.1)
        stdout, stderr = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            kill_group(proc)
    assert sent >= 1, stdout[-2000:] + stderr[-2000:]
    assert proc.returncode == 0, stdout[-3000:] + stderr[-3000:]
    assert "validation: ok" in stdout and "4/4 complete" in stdout
    clean = tmp_path / "clean.zarr"
    r = _dataset(clean)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    a, b = zarr.open_group(str(out), mode="r"), zarr.open_group(str(clean), mode="r")
    for path in ("inputs/radiance", "inputs/features", "layers/radiance", "reference/radiance", "reference/stderr",
                 "guides/albedo", "frames/reference_spp", "frames/nonfinite_inputs"):
        np.testing.assert_array_equal(a[path][:], b[path][:], err_msg=path)


def test_ctrl_c_pressed_five_times_is_one_line_on_stderr(tmp_path):
    """Five presses 0.1 s apart once the cluster is up (its line on stdout): exit 130 and one line, on stderr
    and last, ``interrupted: complete frames stay in STORE; ...``. Before, the run printed that line on
    stdout and then a bare ``interrupted`` on stderr, and a press while the cluster closed left it to close
    at exit: a traceback from an atexit callback, or the process ended by SIGINT (exit -2)."""
    from procs import Command, last_line, python_m
    out = tmp_path / "s.zarr"
    proc = Command(python_m("pipeline") + ["dataset", "--config", str(SMOKE), "--out", str(out), "--no-progress"],
                   env=_env())
    try:
        proc.wait_for("cluster: ")
        proc.ctrl_c(presses=5)
    except BaseException:
        kill_group(proc)
        raise
    code, stdout, err = proc.finish(timeout=120)
    assert code == 130, stdout[-2000:] + err[-3000:]
    last_line(err, f"interrupted: complete frames stay in {out}; run the same command again to resume")
    assert "interrupted" not in stdout, stdout[-2000:]


# ---- 9: a full disk --------------------------------------------------------------------------------
def test_a_full_disk_is_one_line_with_its_own_exit_code_and_the_store_resumes(small_disk):
    filler = small_disk / "filler"
    free = os.statvfs(small_disk).f_bavail * os.statvfs(small_disk).f_frsize
    filler.write_bytes(b"\0" * (free - 160 * 1024))  # room for the store's metadata and a frame or two, not 4
    out = small_disk / "s.zarr"
    r = _dataset(out)
    assert r.returncode == 4, r.stdout[-2000:] + r.stderr[-3000:]
    line = _one_line_error(r)
    assert f"no space left on the device of the store {out}" in line and "free there" in line
    assert "the same command resumes" in line
    filler.unlink()
    r = _dataset(out)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-3000:]
    assert "4/4 complete" in r.stdout and "validation: ok" in r.stdout


@pytest.mark.parametrize("command", ["train", "evaluate", "export"])
def test_a_full_disk_under_any_commands_output_is_exit_4_in_one_line(small_disk, tmp_path, command):
    """train (its checkpoint), evaluate (its JSON) and export (its files) on a full disk: one line naming
    the file and the free space there, exit 4 (as dataset), never an ENOSPC traceback and exit 1."""
    from test_training import make_store
    store = make_store(tmp_path / "s.zarr", h=16, w=16, spp=2, per_split=(2, 1, 1))
    free = os.statvfs(small_disk).f_bavail * os.statvfs(small_disk).f_frsize
    (small_disk / "filler").write_bytes(b"\0" * free)
    argv = {"train": ["training", "train", "--model", "nbg", "--store", str(store), "--steps", "1", "--crop", "8",
                      "--batch", "1", "--out", str(small_disk / "run"), "--no-progress"],
            "evaluate": ["training", "evaluate", "--checkpoint", "input", "--store", str(store), "--out",
                         str(small_disk / "e.json"), "--no-flip"],
            "export": ["pipeline", "export", str(store), "--format", "exr", "--out", str(small_disk / "exr")]}[command]
    r = subprocess.run([sys.executable, "-m", *argv], env=_env(), cwd=ROOT, capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 4, r.stdout[-2000:] + r.stderr[-3000:]
    line = _one_line_error(r)
    assert "no space left on the device" in line and str(small_disk) in line, line
    if command == "train":          # only a training run resumes from its checkpoint
        assert line.endswith("free space and run the same command again: the run resumes from its last "
                             "checkpoint.pt"), line
    else:
        assert line.endswith("free space and run it again") and "checkpoint" not in line, line


# ---- a commit killed between zarr's temporary file and its rename ----------------------------------------
def test_a_resume_removes_the_temporary_file_a_killed_commit_left_and_validate_names_it(tmp_path):
    """zarr's local store writes a key to ``KEY.<uuid>.partial`` and renames it; a SIGKILL in between leaves
    ``status/complete/c/0.<uuid>.partial``. validate names it (a note, not a problem: the key keeps its
    previous bytes), the resume removes it and says so, and the store validates with nothing left over."""
    import uuid
    out = tmp_path / "s.zarr"
    assert _dataset(out).returncode == 0
    left = out / "status" / "complete" / "c" / f"0.{uuid.uuid4().hex}.partial"
    left.write_bytes(b"\x01" * 16)
    v = subprocess.run([PY, "-m", "pipeline", "validate", str(out)], env=_env(), cwd=ROOT, capture_output=True,
                       text=True, timeout=300)
    assert v.returncode == 0 and f"note: 1 temporary file(s) of a write cut short (status/complete/c/{left.name})" \
        in v.stdout, v.stdout + v.stderr
    r = _dataset(out)
    assert r.returncode == 0 and "validation: ok" in r.stdout, r.stdout[-2000:] + r.stderr[-2000:]
    assert f"resume: removed 1 temporary file(s) of a write cut short (status/complete/c/{left.name})" in r.stdout
    assert not left.exists() and not list(out.rglob("*.partial"))
    v = subprocess.run([PY, "-m", "pipeline", "validate", str(out)], env=_env(), cwd=ROOT, capture_output=True,
                       text=True, timeout=300)
    assert v.returncode == 0 and v.stdout.strip().endswith("OK") and "temporary" not in v.stdout, v.stdout
