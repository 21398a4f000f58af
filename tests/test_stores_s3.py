"""Stores at ``s3://`` URLs, against a real S3 protocol server the tests start (moto's server mode, as
zarr-python and s3fs test their own S3 code): a dataset run written, killed, resumed and equal to a local
run; the lease that keeps a second run out and is taken over from a dead one; a missing or corrupted
object named, never read as zeros; export and training (DataLoader worker processes) from the URL; and
no credential anywhere in what the commands print or store.

Endpoint and credentials reach every process through the standard AWS environment variables."""
from __future__ import annotations

import json
import logging
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("s3fs", reason="stores at s3:// URLs need s3fs (pip install -e .[s3])")
moto_server = pytest.importorskip("moto.server", reason="the S3 tests need moto's server (pip install -e .[dev])")

from procs import kill_group  # noqa: E402
from test_pipeline_safety import _env  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
SMOKE = ROOT / "configs" / "smoke.yaml"
SECRET = "s3cr3t-value-that-must-not-leak-0123456789"
BUCKET = "denoise-tests"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class _S3:
    """A moto S3 server on 127.0.0.1 that a test can stop and start again on the same port, with the same
    data (moto keeps it in this process); calling it gives a fresh ``s3://`` URL in the test bucket."""

    def __init__(self):
        self.port = _free_port()
        self.endpoint = f"http://127.0.0.1:{self.port}"
        self.srv = None
        self.n = iter(range(10 ** 6))

    def start(self) -> None:
        self.srv = moto_server.ThreadedMotoServer(ip_address="127.0.0.1", port=self.port, verbose=False)
        self.srv.start()

    def stop(self) -> None:
        self.srv.stop()
        self.srv = None

    def __call__(self, name: str, bucket: str = BUCKET) -> str:
        return f"s3://{bucket}/{name}-{next(self.n)}.zarr"


@pytest.fixture(scope="module")
def s3():
    """A moto S3 server (:class:`_S3`), the AWS_* environment pointing at it (restored afterwards) and a
    bucket."""
    logging.getLogger("werkzeug").setLevel(logging.ERROR)
    server = _S3()
    server.start()
    env = {"AWS_ENDPOINT_URL": server.endpoint, "AWS_ACCESS_KEY_ID": "testing-key-id",
           "AWS_SECRET_ACCESS_KEY": SECRET, "AWS_DEFAULT_REGION": "us-east-1"}
    saved = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    try:
        import boto3
        boto3.client("s3").create_bucket(Bucket=BUCKET)
        yield server
    finally:
        if server.srv is not None:
            server.stop()
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _objects(prefix_url: str) -> dict[str, bytes]:
    import boto3
    s3 = boto3.client("s3")
    bucket, _, prefix = prefix_url.split("://", 1)[1].partition("/")
    out = {}
    for page in s3.get_paginator("list_objects_v2").paginate(Bucket=bucket, Prefix=prefix):
        for o in page.get("Contents", []):
            out[o["Key"]] = s3.get_object(Bucket=bucket, Key=o["Key"])["Body"].read()
    return out


def _dataset(out, *extra, timeout=600) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "pipeline", "dataset", "--config", str(SMOKE), "--out", str(out),
                           "--no-progress", *extra], env=_env(), cwd=ROOT, capture_output=True, text=True,
                          timeout=timeout)


def _arrays(store) -> dict:
    import zarr
    g = zarr.open_group(str(store), mode="r")
    return {f"{grp}/{name}": a[...] for grp, sub in g.groups() for name, a in sub.arrays()}


# ---- a dataset run on S3: its endpoint goes away, comes back, the store resumes and equals a local run ----
def _keys(prefix_url: str) -> list[str]:
    import boto3
    bucket, _, prefix = prefix_url.split("://", 1)[1].partition("/")
    pages = boto3.client("s3").get_paginator("list_objects_v2").paginate(Bucket=bucket, Prefix=prefix)
    return [o["Key"] for page in pages for o in page.get("Contents", [])]


def test_a_dataset_on_s3_outlives_its_endpoint_going_away_and_equals_a_local_run(s3, tmp_path):
    """The S3 server stops while a run renders into its store: after botocore's retries (a short window
    here, AWS_MAX_ATTEMPTS=2) the run stops with one line naming the endpoint and the last error (exit 5,
    no traceback), leaving its lease behind; with the server back (same data) the same command takes the
    lease over, resumes and makes a store equal to a local run's. Back empty (the store's bucket gone),
    validate finds no store and the run names the missing bucket (exit 2); nothing prints a credential."""
    import boto3
    boto3.client("s3").create_bucket(Bucket="denoise-gone")
    url = s3("smoke", bucket="denoise-gone")
    env = {**_env(), "AWS_MAX_ATTEMPTS": "2"}
    proc = subprocess.Popen([sys.executable, "-m", "pipeline", "dataset", "--config", str(SMOKE), "--out", url,
                             "--no-progress"], env=env, cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        t0 = time.monotonic()           # the scenes' JSON is stored: the store is made and frames render now
        while proc.poll() is None and time.monotonic() - t0 < 300 and not any(
                "/frames/scene_json/c/" in k for k in _keys(url)):
            time.sleep(0.2)
        s3.stop()
        out, err = proc.communicate(timeout=300)
        first = out + err
    finally:
        kill_group(proc)
        if s3.srv is None:
            s3.start()
    errors = [ln for ln in first.splitlines() if ln.startswith("error:")]
    assert proc.returncode == 5 and len(errors) == 1, first[-3000:]
    assert err.splitlines() == errors, err[-3000:]          # the one line and nothing else (asyncio's included)
    assert s3.endpoint in errors[0] and "could not be reached" in errors[0] and "EndpointConnectionError" in errors[0]
    assert "run the same command again" in errors[0] and "Traceback" not in first, first[-6000:]
    assert any(k.endswith("/dataset.lock") for k in _keys(url))      # it could not delete its lease
    r = _dataset(url)
    assert r.returncode == 0, first[-2000:] + r.stdout[-3000:] + r.stderr[-3000:]
    assert "4/4 complete" in r.stdout and "validation: ok" in r.stdout
    assert "took over" in r.stdout and "lease" not in r.stderr      # the stopped run's lease was taken over
    local = tmp_path / "local.zarr"
    assert _dataset(local).returncode == 0
    a, b = _arrays(url), _arrays(local)
    assert a.keys() == b.keys()
    for k in a:
        if k == "frames/render_seconds":
            continue
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)
    v = subprocess.run([sys.executable, "-m", "pipeline", "validate", url], env=_env(), cwd=ROOT,
                       capture_output=True, text=True, timeout=300)
    assert v.returncode == 0 and v.stdout.strip().endswith("OK"), v.stdout[-2000:] + v.stderr
    for text in (first, r.stdout, r.stderr, v.stdout, v.stderr):         # no credential in any output...
        assert SECRET not in text and "testing-key-id" not in text
    assert not any(SECRET.encode() in body for body in _objects(url).values())   # ...nor in the store
    # back empty: the store (here its whole bucket) is gone
    s3c = boto3.client("s3")
    for k in _keys("s3://denoise-gone/"):
        s3c.delete_object(Bucket="denoise-gone", Key=k)
    s3c.delete_bucket(Bucket="denoise-gone")
    v = subprocess.run([sys.executable, "-m", "pipeline", "validate", url], env=_env(), cwd=ROOT,
                       capture_output=True, text=True, timeout=300)
    assert v.returncode == 2 and f"no store at {url}" in v.stderr, v.stderr
    r = _dataset(url, timeout=120)
    assert r.returncode == 2 and "bucket 'denoise-gone'" in r.stderr and "does not exist" in r.stderr, r.stderr
    assert "Traceback" not in r.stderr and "dashboard" not in r.stdout


# ---- the lease ----------------------------------------------------------------------------------------
def _lease_key(url: str) -> str:
    return url.split(f"s3://{BUCKET}/", 1)[1] + "/dataset.lock"


def test_a_second_run_is_refused_while_the_lease_lives_and_a_dead_lease_is_taken_over(s3):
    import boto3

    from stores.errors import StoreLockedError
    from stores.lock import S3Lease, StoreLock
    url = s3("locked")
    lock = StoreLock(url, command="the first run").acquire()
    try:
        r = _dataset(url, timeout=120)
        assert r.returncode == 2, r.stdout + r.stderr
        assert f"is in use by another dataset run: pid {os.getpid()} on host {socket.gethostname()}" in r.stderr
        assert "(the first run)" in r.stderr and "lease object" in r.stderr and "dashboard" not in r.stdout
    finally:
        lock.release()
    assert not _objects(url)                                        # released: the lease object is gone
    # leases of other hosts, judged by the object store's clock, never by the time a holder wrote in them
    s3c, key = boto3.client("s3"), _lease_key(url)
    behind = {"host": "elsewhere", "pid": 76, "started": "then", "expires": time.time() - 3600, "lease_s": 60}
    s3c.put_object(Bucket=BUCKET, Key=key, Body=json.dumps(behind).encode())    # renewed now, by a slow clock
    with pytest.raises(StoreLockedError, match="pid 76 on host elsewhere.* lasts (59|60) s more"):
        StoreLock(url).acquire()
    ahead = {"host": "elsewhere", "pid": 77, "started": "then", "expires": time.time() + 3600, "lease_s": 1}
    s3c.put_object(Bucket=BUCKET, Key=key, Body=json.dumps(ahead).encode())     # a fast clock, not renewed
    stale = s3c.head_object(Bucket=BUCKET, Key=key)["ETag"]
    time.sleep(2.1)                                                  # LastModified counts whole seconds
    a = StoreLock(url).acquire()
    try:
        assert a.took_over["pid"] == 77
        # two runs racing for the same dead lease: the one whose If-Match ETag is stale loses
        b = S3Lease(url, {"host": "b", "pid": 2})
        with pytest.raises(Exception) as e:
            b.s3.put_object(Bucket=BUCKET, Key=key, Body=b"{}", IfMatch=stale)
        assert b._failed(e.value)
        with pytest.raises(StoreLockedError, match="in use by another dataset run"):
            b.acquire()
    finally:
        a.release()


def _short_lock(url: str, lease: float):
    """A StoreLock holding an S3 lease of ``lease`` seconds (renewed every third of it)."""
    from stores.lock import S3Lease, StoreLock
    lock = StoreLock(url)
    lock._lease = S3Lease(url, lock._record(), lease=lease).acquire()
    return lock


def test_a_run_whose_lease_is_taken_over_stops_writing_and_leaves_the_new_lease(s3):
    """A renewal refused for real (another writer's lease replaced this one): the next commit's check
    raises, and the release deletes nothing (DELETE If-Match on this run's ETag)."""
    import boto3

    from stores.errors import StoreLockedError
    url = s3("lost")
    lock = _short_lock(url, 1.5)
    lock.check()                                                      # held: nothing to say
    thief = b'{"host": "thief", "pid": 1, "lease_s": 60}'
    boto3.client("s3").put_object(Bucket=BUCKET, Key=_lease_key(url), Body=thief)
    t0 = time.monotonic()
    while lock._lease.lost is None and time.monotonic() - t0 < 10:
        time.sleep(0.1)
    with pytest.raises(StoreLockedError, match="taken over by another run"):
        lock.check()
    lock.release()
    assert _objects(url)[_lease_key(url)] == thief
    # a lease released while still ours is deleted, but only by its own ETag
    mine = _short_lock(s3("mine"), 60)
    mine._lease.etag = '"0123456789abcdef0123456789abcdef"'          # as if another run had renewed it since
    mine.release()
    assert len(_objects(mine.store)) == 1


def test_a_release_during_a_renewal_deletes_the_renewed_lease(s3):
    """The renewal's PUT has reached the server (a new ETag there) but its answer has not come back when
    the run releases: the release waits for it and deletes the lease by the new ETag, rather than miss
    with the old one and leave a live-looking lease for a minute. Each renewal's ETag differs here, as a
    server's does where the ETag is not the body's MD5 (SSE-KMS, SSE-C)."""
    import itertools
    import threading
    url = s3("released")
    lock = _short_lock(url, 0.6)                                      # renewed every 0.2 s
    lease, put, in_flight, n = lock._lease, lock._lease._put, threading.Event(), itertools.count()

    def slow_answer(**cond):
        lease.record = {**lease.record, "renewal": next(n)}          # another body: another ETag
        etag = put(**cond)
        if threading.current_thread().name == "store-lease":
            in_flight.set()
            time.sleep(0.5)                                           # written there, the answer still on its way
        return etag

    lease._put = slow_answer
    assert in_flight.wait(10)
    lock.release()
    assert _lease_key(url) not in _objects(url)


def test_a_run_that_cannot_renew_its_lease_stops_writing_before_it_expires(s3):
    """The endpoint goes away: renewals fail for real, and once the lease has gone unrenewed for half its
    length the run's check raises StoreUnreachableError (exit 5), before another run could take it."""
    from stores.errors import StoreUnreachableError
    url = s3("unrenewed")
    lock = _short_lock(url, 3.0)
    s3.stop()
    try:
        time.sleep(0.5)
        lock.check()                                                  # within half the lease: still held
        t0 = time.monotonic()
        while lock._lease.lost is None and time.monotonic() - t0 < 20:
            time.sleep(0.1)
        with pytest.raises(StoreUnreachableError, match="could not renew the lease .* for [12] s of its 3 s"):
            lock.check()
        assert time.monotonic() - lock._lease.renewed_at < 3.0           # said before the lease could end
        lock.release()                                                # no connection: no error either
    finally:
        s3.start()


# ---- integrity: a missing or corrupted object is named, never zeros -----------------------------------
@pytest.fixture(scope="module")
def synthetic_s3(s3):
    from test_training import make_store
    url = s3("synthetic")
    make_store(url, h=16, w=16, spp=2, per_split=(3, 1, 1))
    return url


def test_a_missing_or_corrupted_object_is_named_never_zeros(s3, capsys):
    import boto3

    from pipeline.__main__ import main
    from stores.errors import CorruptChunkError, MissingShardError
    from stores.reader import open_store
    from test_training import make_store
    url = make_store(s3("damaged"), h=16, w=16, spp=2, per_split=(2, 1, 1))
    s3c = boto3.client("s3")
    prefix = url.split(f"s3://{BUCKET}/", 1)[1]
    gone = f"{prefix}/guides/depth/c/1/0/0"
    s3c.delete_object(Bucket=BUCKET, Key=gone)
    assert main(["validate", url]) == 3
    out = capsys.readouterr().out
    assert f"guides/depth: frame 1 is complete but its chunk file s3://{BUCKET}/{gone} is missing" in out, out
    with pytest.raises(MissingShardError, match="guides/depth: frame 1") as e:
        open_store(url).read_frame(1)
    assert e.value.path == f"s3://{BUCKET}/{gone}"
    key = f"{prefix}/layers/radiance/c/2/0/0/0/0"
    body = bytearray(s3c.get_object(Bucket=BUCKET, Key=key)["Body"].read())
    body[20] ^= 0x10
    s3c.put_object(Bucket=BUCKET, Key=key, Body=bytes(body))
    with pytest.raises(CorruptChunkError, match="layers/radiance: frame 2"):
        open_store(url).read_frame(2)
    assert main(["validate", url]) == 3
    assert "layers/radiance: frame 2" in capsys.readouterr().out


def _exit_code(e: BaseException) -> int:
    """What a command exits with for ``e`` (``core.cli``, through the stores' ``explain``)."""
    from core.cli import exit_code
    from stores.errors import explain
    return exit_code(explain(e) or e)


def test_an_endpoint_gone_while_reading_is_unreachable_never_damage(s3, synthetic_s3, monkeypatch, tmp_path):
    """The endpoint goes away after the store was opened (mid-training, mid-validate): a read ends in
    StoreUnreachableError naming the endpoint (exit 5), never CorruptChunkError (damage, exit 3, which
    `validate --mark-damaged` would write into the store). validate, train and evaluate on a store whose
    endpoint is gone exit 5 with one line and no traceback."""
    import s3fs

    from stores.errors import StoreUnreachableError
    from stores.reader import open_store
    from stores.writer import complete_flags
    monkeypatch.setenv("AWS_MAX_ATTEMPTS", "1")
    s3fs.S3FileSystem.clear_instance_cache()                         # a client with the short retry window
    st = open_store(synthetic_s3)
    st.read_frame(0)                                                  # its metadata read: mid-run
    s3.stop()
    try:
        with pytest.raises(StoreUnreachableError, match="could not be reached") as e:
            st.read_frame(1)
        assert _exit_code(e.value) == 5 and s3.endpoint in str(e.value)
        with pytest.raises(Exception) as e:                          # not "every frame incomplete"
            complete_flags(st.root)
        assert _exit_code(e.value) == 5
        runs = {"validate": ["pipeline", "validate", synthetic_s3],
                "train": ["training", "train", "--model", "nbg", "--store", synthetic_s3, "--steps", "1", "--crop",
                          "8", "--batch", "1", "--out", str(tmp_path / "run"), "--no-progress"],
                "evaluate": ["training", "evaluate", "--checkpoint", "input", "--store", synthetic_s3, "--out",
                             str(tmp_path / "e.json"), "--no-flip"]}
        for name, argv in runs.items():
            r = subprocess.run([sys.executable, "-m", *argv], env=_env(AWS_MAX_ATTEMPTS="1"), cwd=ROOT,
                               capture_output=True, text=True, timeout=300)
            errors = [ln for ln in r.stderr.splitlines() if ln.startswith("error:")]
            assert r.returncode == 5 and len(errors) == 1 and "Traceback" not in r.stderr, (name, r.stderr[-3000:])
            assert "leaked semaphore" not in r.stderr, (name, r.stderr[-3000:])       # nothing after the line
            assert s3.endpoint in errors[0] and "could not be reached" in errors[0], (name, errors)
    finally:
        s3.start()
        s3fs.S3FileSystem.clear_instance_cache()


ABANDONED_BATCH = """
import argparse, sys, zarr
from core.cli import Program, run_main
from stores.commands import explain, setup


def read(args):
    a = zarr.open_array(sys.argv[1], mode="r")
    a[:2]
    print("open", flush=True)
    sys.stdin.readline()                # the test stops the endpoint
    a[:]                                # 64 chunks at once: the first to fail abandons the others


def parser(argv):
    p = argparse.ArgumentParser()
    p.set_defaults(run=read)
    return p


sys.exit(run_main(Program(parser=parser, setup=setup, explain=lambda e, args: explain(e, sys.argv[1])), []))
"""


def test_an_endpoint_lost_under_a_batch_of_requests_is_one_line_and_nothing_after_it(s3):
    """A read of many chunks whose endpoint goes away: the first request to spend its retries ends the
    command (exit 5, its one line), the others of the batch still waiting out botocore's back-off on
    zarr's event loop. They are cancelled at exit: no "Task was destroyed but it is pending!" (two lines
    each, from asyncio's logger when zarr closes its loop) after the command's line."""
    import s3fs
    import zarr
    url = s3("batch")
    zarr.create_array(url, shape=(64, 8), chunks=(1, 8), dtype="f4")[:] = 1
    proc = subprocess.Popen([sys.executable, "-c", ABANDONED_BATCH, url], env=_env(AWS_MAX_ATTEMPTS="3"), cwd=ROOT,
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    try:
        assert proc.stdout.readline() == "open\n", proc.stderr.read()[-3000:] if proc.poll() is not None else ""
        s3.stop()
        out, err = proc.communicate("go\n", timeout=300)
    finally:
        kill_group(proc)
        if s3.srv is None:
            s3.start()
        s3fs.S3FileSystem.clear_instance_cache()
    lines = err.splitlines()
    assert proc.returncode == 5 and len(lines) == 1, err[-3000:]
    assert lines[0].startswith("error: the object store of ") and s3.endpoint in lines[0], lines[0]


# ---- export and training from S3 ------------------------------------------------------------------------
def test_export_and_training_read_from_s3_what_a_local_copy_holds(synthetic_s3, tmp_path):
    from pipeline.__main__ import main
    from core.images import read_exr
    from stores.reader import open_store
    from test_training import make_store
    from training.data import batch_loader, model_dataset
    from training.inputs import InputSpec
    local = make_store(tmp_path / "local.zarr", h=16, w=16, spp=2, per_split=(3, 1, 1))
    assert main(["export", synthetic_s3, "--format", "exr", "--frames", "0", "--out", str(tmp_path / "e")]) == 0
    np.testing.assert_array_equal(read_exr(tmp_path / "e" / "frame_000000" / "reference.exr")[0],
                                  open_store(local).read_frame(0, ["reference"])["reference"])
    spec = InputSpec("samples", 1, 2)
    got = [next(iter(batch_loader(model_dataset(spec, s, "train", 2, 8, True, 3), 2, 3, 0, 1, workers=w)))
           for s, w in ((synthetic_s3, 1), (local, 0))]                 # a DataLoader worker process for S3
    for k in got[1]:
        if hasattr(got[1][k], "shape"):
            np.testing.assert_array_equal(np.asarray(got[0][k]), np.asarray(got[1][k]), err_msg=k)
    r = subprocess.run([sys.executable, "-m", "training", "train", "--model", "nbg", "--store", synthetic_s3,
                        "--steps", "2", "--crop", "8", "--batch", "2", "--workers", "1", "--out",
                        str(tmp_path / "run"), "--no-progress"], env=_env(), cwd=ROOT, capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0 and (tmp_path / "run" / "checkpoint.pt").exists(), r.stderr[-3000:]
    assert SECRET not in r.stdout + r.stderr


def test_an_endpoint_gone_inside_a_first_commit_leaves_the_frame_incomplete_not_damaged(s3, monkeypatch, capsys):
    """The endpoint dies during the PUT of a chunk's first completion flags (after status/error was
    written), in the store's first chunk and one past a chunk boundary: the write ends unreachable (exit
    5); with the endpoint back, validate says incomplete (exit 1), never damaged (exit 3), and the frame
    is written again."""
    import s3fs

    import stores.writer as writer_mod
    from pipeline.__main__ import main
    from stores import schema
    from stores.reader import open_store
    from stores.schema import StoreLayout
    from stores.writer import StoreWriter, open_or_create
    from test_stores_synthetic import synthetic_frame
    monkeypatch.setenv("AWS_MAX_ATTEMPTS", "1")
    s3fs.S3FileSystem.clear_instance_cache()
    url = s3("first-commit")
    w = open_or_create(url, StoreLayout(num_frames=schema.META_CHUNK + 2, height=8, width=8, spp=2, tile=8), {})
    real = writer_mod._set_many

    def endpoint_dies_at_the_flags(arr, values):
        if arr.path == "status/complete" and any(v is True for _, v in values):
            s3.stop()
        return real(arr, values)
    try:
        for frame in (0, schema.META_CHUNK + 1):
            monkeypatch.setattr(writer_mod, "_set_many", endpoint_dies_at_the_flags)
            with pytest.raises(Exception) as e:
                w.write_frame(frame, synthetic_frame(frame, 8, 8, 2, motion=False))
            assert _exit_code(e.value) == 5, repr(e.value)
            monkeypatch.setattr(writer_mod, "_set_many", real)
            s3.start()
            s3fs.S3FileSystem.clear_instance_cache()
            w = StoreWriter(url)
            assert main(["validate", url, "--frames", str(frame)]) == 1
            text = capsys.readouterr().out
            assert "incomplete" in text and "DAMAGED" not in text, text
            w.write_frame(frame, synthetic_frame(frame, 8, 8, 2, motion=False))
            assert open_store(url).frames_meta(frame)["complete"]
    finally:
        if s3.srv is None:
            s3.start()
        s3fs.S3FileSystem.clear_instance_cache()
