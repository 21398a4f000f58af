"""One writer per store: the lock a ``dataset`` run holds on its store for as long as it runs.

``StoreLock(store)`` is a file ``<store>/dataset.lock`` holding the holder's host, pid, process start
time and start time (JSON), with a kernel ``flock`` on it while the run lives::

    with StoreLock(store) as lock:      # StoreLockedError if another run holds it
        ...                            # create / resume the store, render, validate

- A second run on the same store is refused (:class:`~stores.errors.StoreLockedError` naming the
  holder's host, pid and start) while the first one lives.
- A lock left behind by a dead process on this host (its pid is gone, a zombie, or reused by a
  process that started later) is taken over; the kernel drops the ``flock`` of a dead process, so
  two runs racing for a stale lock cannot both win.
- A lock from another host cannot be checked from here: it is refused, and the message says which
  file to delete if that run is known to be dead.
- Stores at ``s3://`` URLs are locked by a **lease object** ``<store>/dataset.lock`` (:class:`S3Lease`):
  created with a conditional PUT (``If-None-Match: *``), so of two runs exactly one creates it (S3
  conditional writes are atomic and S3 reads are strongly consistent); the holder renews it (a PUT with
  ``If-Match`` on its ETag) every ``LEASE_SECONDS / 3`` while it runs and deletes it at the end. A
  lease not renewed for ``LEASE_SECONDS`` (its run was killed), or held by a dead process of this host,
  is taken over with a PUT ``If-Match`` on
  the ETag the taker read, so two runs racing for a dead lease cannot both win. A holder whose renewal
  fails (it stalled past its lease and another run took over) knows it has lost the store: its next
  commit raises (``StoreLock.check``). Other URL protocols have no lock (``StoreLock.supported`` False):
  one run at a time is then up to the user.
"""
from __future__ import annotations

import fcntl
import json
import os
import socket
import time

from stores.errors import StoreLockedError, StorePathError, is_disk_full, store_full
from stores.procinfo import holder_record, pid_alive
from stores.schema import LOCK_NAME


def _path_error(store: str, what: str, e: OSError) -> StorePathError:
    return StorePathError(f"store path {store}: {what}: {e.strerror or e} (is a parent a file, or the folder "
                          f"read-only?); choose another path")


def describe(holder: dict) -> str:
    return (f"pid {holder.get('pid')} on host {holder.get('host')}, started {holder.get('started')}"
            + (f" ({holder.get('command')})" if holder.get("command") else ""))


LEASE_SECONDS = 60.0        # an S3 lease not renewed for this long belongs to a dead run


class S3Lease:
    """The writer lock of a store at an ``s3://`` URL (module docstring): a lease object renewed while
    the run lives. Endpoint and credentials come from the standard AWS environment and config files
    (botocore), never from the store; messages name the URL and the holder, never a credential."""

    def __init__(self, url: str, record: dict, lease: float = LEASE_SECONDS):
        bucket_key = url.split("://", 1)[1].rstrip("/")
        self.url = url.rstrip("/") + "/" + LOCK_NAME
        self.bucket, _, prefix = bucket_key.partition("/")
        self.key = f"{prefix}/{LOCK_NAME}" if prefix else LOCK_NAME
        self.record, self.lease = dict(record), float(lease)
        self.etag: str | None = None
        self.took_over: dict | None = None
        self.lost: str | None = None
        self._stop = None
        import boto3
        self.s3 = boto3.client("s3")

    def _body(self) -> bytes:
        return json.dumps({**self.record, "expires": time.time() + self.lease, "lease_s": self.lease}).encode()

    def _failed(self, e) -> bool:
        """Whether ``e`` is a refused conditional write (another run's lease is there)."""
        code = getattr(e, "response", {}).get("Error", {}).get("Code", "")
        return code in ("PreconditionFailed", "412", "ConditionalRequestConflict")

    def _holder(self) -> tuple[dict | None, str | None]:
        try:
            r = self.s3.get_object(Bucket=self.bucket, Key=self.key)
        except self.s3.exceptions.NoSuchKey:
            return None, None
        try:
            d = json.loads(r["Body"].read().decode())
        except ValueError:
            d = None
        return (d if isinstance(d, dict) else {}), r["ETag"]

    def acquire(self) -> "S3Lease":
        for _ in range(5):
            try:
                self.etag = self.s3.put_object(Bucket=self.bucket, Key=self.key, Body=self._body(),
                                               IfNoneMatch="*")["ETag"]
                break
            except Exception as e:  # noqa: BLE001 - botocore's ClientError
                if not self._failed(e):
                    raise
            holder, etag = self._holder()
            if holder is None:
                continue                        # released in between: try to create it again
            left = float(holder.get("expires", 0)) - time.time()
            dead_here = (holder.get("host") == socket.gethostname() and holder.get("pid") != os.getpid()
                         and not pid_alive(holder.get("pid", -1), holder.get("proc_start")))
            if left > 0 and not dead_here:      # alive, or on another host and within its lease
                until = time.strftime("%H:%M:%SZ", time.gmtime(float(holder["expires"])))
                raise StoreLockedError(
                    f"the store {self.url.rsplit('/', 1)[0]} is in use by another dataset run: {describe(holder)}; "
                    f"its lease object {self.url} runs until {until} and is renewed while that run lives "
                    "(wait for it to finish, or stop it)", holder=holder)
            try:                                # expired: take it over, unless another run does first
                self.etag = self.s3.put_object(Bucket=self.bucket, Key=self.key, Body=self._body(),
                                               IfMatch=etag)["ETag"]
                self.took_over = holder
                break
            except Exception as e:  # noqa: BLE001
                if not self._failed(e):
                    raise
        else:
            raise StoreLockedError(f"could not take the lease {self.url}: it kept changing under this run")
        import threading
        self._stop = threading.Event()
        threading.Thread(target=self._renew, name="store-lease", daemon=True).start()
        return self

    def _renew(self) -> None:
        while not self._stop.wait(self.lease / 3):
            try:
                self.etag = self.s3.put_object(Bucket=self.bucket, Key=self.key, Body=self._body(),
                                               IfMatch=self.etag)["ETag"]
            except Exception as e:  # noqa: BLE001
                if self._failed(e):
                    self.lost = (f"the lease {self.url} was taken over by another run (this run did not renew "
                                 f"it within {self.lease:g} s); this run stops writing the store")
                    return
                # a network error: try again next time; the lease lasts 3 renewal periods

    def release(self) -> None:
        if self._stop is not None:
            self._stop.set()
        if self.lost or self.etag is None:
            return
        holder, etag = self._holder()
        if etag == self.etag:                   # still ours: delete it
            self.s3.delete_object(Bucket=self.bucket, Key=self.key)
        self.etag = None


class StoreLock:
    """The writer lock of the store at ``store``: a lock file with ``flock`` for a local path, a lease
    object for an ``s3://`` URL (:class:`S3Lease`); other URLs are not locked (``supported`` False)."""

    def __init__(self, store, command: str | None = None):
        self.store = os.fspath(store)
        self._lease: S3Lease | None = None
        self.supported = "://" not in self.store or self.store.startswith("s3://")
        self.path = os.path.join(self.store, LOCK_NAME)
        self.command = command
        self.took_over: dict | None = None       # the stale holder replaced, if any
        self._fd: int | None = None
        self._made_dir = False                   # the folder was made for the lock: removed if left empty

    # ------------------------------------------------------------------------------------------------
    def _record(self) -> dict:
        return holder_record(command=self.command)

    @staticmethod
    def _read(fd: int) -> dict | None:
        try:
            data = os.pread(fd, 1 << 16, 0)
            d = json.loads(data.decode()) if data.strip() else None
            return d if isinstance(d, dict) else None
        except (OSError, ValueError):
            return None

    def _holder_record(self, fd: int, wait: float = 2.0) -> dict | None:
        """The record of the run that holds the lock. A run that has just taken it writes its record
        right after: wait up to ``wait`` seconds for it rather than report an empty one."""
        deadline = time.monotonic() + wait
        while True:
            holder = self._read(fd)
            if holder or time.monotonic() >= deadline:
                return holder
            time.sleep(0.05)

    def _drop_made_dir(self) -> None:
        """Remove the store's folder if this lock made it and it is still empty."""
        if self._made_dir:
            try:
                os.rmdir(self.store)
            except OSError:
                pass

    def _refuse(self, holder: dict | None, why: str) -> StoreLockedError:
        self._drop_made_dir()
        h = holder or {}
        who = describe(h) if h else "a run that started at the same moment (its record is not written yet)"
        return StoreLockedError(
            f"the store {self.store} is in use by another dataset run: {who}{why}; lock file {self.path}",
            holder=h)

    def acquire(self) -> "StoreLock":
        """Take the lock or raise StoreLockedError. Creates the store's folder if it is missing."""
        if not self.supported or self._fd is not None or self._lease is not None:
            return self
        if "://" in self.store:
            self._lease = S3Lease(self.store, self._record()).acquire()
            self.took_over = self._lease.took_over
            return self
        if not os.path.isdir(self.store):
            try:
                os.makedirs(self.store, exist_ok=True)
            except OSError as e:
                if is_disk_full(e):
                    raise store_full(self.store, "making its folder") from None
                raise _path_error(self.store, "cannot make the store's folder", e) from e
            self._made_dir = True
        me = socket.gethostname()
        for _ in range(20):
            try:
                fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
            except OSError as e:
                self._drop_made_dir()
                raise _path_error(self.store, f"cannot write its lock file {self.path}", e) from e
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = self._holder_record(fd)
                os.close(fd)
                raise self._refuse(holder, "; wait for it to finish (or stop it) and run again") from None
            try:                    # a run that was releasing may have unlinked the file we locked
                same = os.fstat(fd).st_ino == os.stat(self.path).st_ino
            except FileNotFoundError:
                same = False
            if not same:
                os.close(fd)
                continue
            holder = self._read(fd)
            if holder:
                if holder.get("host") != me:
                    os.close(fd)
                    raise self._refuse(holder, f"; it runs on another host, so this one ({me}) cannot tell "
                                               "whether it is alive: if it is not, delete the lock file")
                if pid_alive(holder.get("pid", -1), holder.get("proc_start")) and holder.get("pid") != os.getpid():
                    os.close(fd)
                    raise self._refuse(holder, " (its process is alive but holds no lock: if it is not a "
                                               "dataset run, delete the lock file)")
                self.took_over = holder
            data = json.dumps(self._record()).encode()
            try:
                os.ftruncate(fd, 0)
                os.pwrite(fd, data, 0)
                os.fsync(fd)
            except OSError as e:
                os.close(fd)
                self._drop_made_dir()
                if is_disk_full(e):
                    raise store_full(self.store, f"writing its lock file {self.path}") from None
                raise _path_error(self.store, f"cannot write its lock file {self.path}", e) from e
            self._fd = fd
            return self
        raise StoreLockedError(f"could not take the lock {self.path}: it kept changing under this run")

    def release(self) -> None:
        """Drop the lock and delete the lock file (only if it is still ours), and the store's folder
        if this lock made it and nothing else was put there (a run that stopped before creating)."""
        if self._lease is not None:
            lease, self._lease = self._lease, None
            lease.release()
            return
        fd, self._fd = self._fd, None
        if fd is None:
            return
        try:
            if os.fstat(fd).st_ino == os.stat(self.path).st_ino:
                os.unlink(self.path)
        except OSError:
            pass
        finally:
            os.close(fd)
        self._drop_made_dir()

    @property
    def held(self) -> bool:
        return self._fd is not None or self._lease is not None

    def check(self) -> None:
        """Raise StoreLockedError if this run lost the store (an S3 lease another run took over)."""
        if self._lease is not None and self._lease.lost:
            raise StoreLockedError(self._lease.lost)

    def __enter__(self) -> "StoreLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


def read_lock(store) -> dict | None:
    """The lock record in ``store`` (None if there is none or it is unreadable)."""
    try:
        with open(os.path.join(os.fspath(store), LOCK_NAME)) as f:
            d = json.load(f)
        return d if isinstance(d, dict) else None
    except (OSError, ValueError):
        return None
