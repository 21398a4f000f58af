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
import signal
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


@pytest.fixture(scope="module")
def s3():
    """A moto S3 server on 127.0.0.1, the AWS_* environment pointing at it (restored afterwards) and a
    bucket; yields a function giving a fresh ``s3://`` URL."""
    logging.getLogger("werkzeug").setLevel(logging.ERROR)
    port = _free_port()
    srv = moto_server.ThreadedMotoServer(ip_address="127.0.0.1", port=port, verbose=False)
    srv.start()
    env = {"AWS_ENDPOINT_URL": f"http://127.0.0.1:{port}", "AWS_ACCESS_KEY_ID": "testing-key-id",
           "AWS_SECRET_ACCESS_KEY": SECRET, "AWS_DEFAULT_REGION": "us-east-1"}
    saved = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    try:
        import boto3
        boto3.client("s3").create_bucket(Bucket=BUCKET)
        n = iter(range(10 ** 6))
        yield lambda name: f"s3://{BUCKET}/{name}-{next(n)}.zarr"
    finally:
        srv.stop()
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _objects(prefix_url: str) -> dict[str, bytes]:
    import boto3
    s3 = boto3.client("s3")
    prefix = prefix_url.split(f"s3://{BUCKET}/", 1)[1]
    out = {}
    for page in s3.get_paginator("list_objects_v2").paginate(Bucket=BUCKET, Prefix=prefix):
        for o in page.get("Contents", []):
            out[o["Key"]] = s3.get_object(Bucket=BUCKET, Key=o["Key"])["Body"].read()
    return out


def _dataset(out, *extra, timeout=600) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "pipeline", "dataset", "--config", str(SMOKE), "--out", str(out),
                           "--no-progress", *extra], env=_env(), cwd=ROOT, capture_output=True, text=True,
                          timeout=timeout)


def _arrays(store) -> dict:
    import zarr
    g = zarr.open_group(str(store), mode="r")
    return {f"{grp}/{name}": a[...] for grp, sub in g.groups() for name, a in sub.arrays()}


# ---- a dataset run on S3: killed, resumed, equal to a local run -------------------------------------
def test_a_dataset_on_s3_is_killed_resumed_and_equals_a_local_run(s3, tmp_path):
    url = s3("smoke")
    proc = subprocess.Popen([sys.executable, "-m", "pipeline", "dataset", "--config", str(SMOKE), "--out", url,
                             "--no-progress"], env=_env(), cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, start_new_session=True)
    import zarr
    try:
        t0, done = time.monotonic(), 0
        while proc.poll() is None and time.monotonic() - t0 < 300 and not done:
            try:
                done = int(zarr.open_group(url, mode="r")["status/complete"][:].sum())
            except Exception:  # noqa: BLE001 - not created yet
                pass
            time.sleep(0.3)
    finally:
        kill_group(proc)                     # SIGKILL mid-run (after its first commit, or before it)
    first = proc.stdout.read()
    r = _dataset(url)
    assert r.returncode == 0, first[-2000:] + r.stdout[-3000:] + r.stderr[-3000:]
    assert "4/4 complete" in r.stdout and "validation: ok" in r.stdout
    assert "took over" in r.stdout and "lease" not in r.stderr      # the killed run's lease was taken over
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


# ---- the lease ----------------------------------------------------------------------------------------
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
    # a run killed while holding it: its lease expired (written by hand here, 1 s old)
    s3c = boto3.client("s3")
    key = url.split(f"s3://{BUCKET}/", 1)[1] + "/dataset.lock"
    dead = {"host": "elsewhere", "pid": 77, "started": "then", "expires": time.time() - 1}
    s3c.put_object(Bucket=BUCKET, Key=key, Body=json.dumps(dead).encode())
    stale = s3c.head_object(Bucket=BUCKET, Key=key)["ETag"]
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


def test_a_run_that_lost_its_lease_writes_nothing_more(s3):
    from stores.errors import StoreLockedError
    from stores.lock import S3Lease, StoreLock
    url = s3("lost")
    lock = StoreLock(url).acquire()
    lease = lock._lease
    lease.s3.put_object(Bucket=BUCKET, Key=lease.key, Body=b'{"host": "thief", "pid": 1, "expires": 1e12}')
    lease._stop.set()
    with pytest.raises(Exception) as e:                   # what the renewal thread meets
        lease.s3.put_object(Bucket=BUCKET, Key=lease.key, Body=b"{}", IfMatch=lease.etag)
    assert isinstance(lease, S3Lease) and lease._failed(e.value)
    lease.lost = "the lease was taken over"
    with pytest.raises(StoreLockedError, match="taken over"):
        lock.check()


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


# ---- export and training from S3 ------------------------------------------------------------------------
def test_export_and_training_read_from_s3_what_a_local_copy_holds(synthetic_s3, tmp_path):
    from pipeline.__main__ import main
    from stores.imageio import read_exr
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
