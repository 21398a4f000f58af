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
  ``If-Match`` on its ETag) every ``LEASE_SECONDS / 3`` while it runs and deletes it at the end (a
  ``DELETE`` with ``If-Match``: only its own). A lease not renewed for ``LEASE_SECONDS`` by the object
  store's clock (its ``LastModified`` against the ``Date`` of the response that read it: the hosts'
  clocks never meet), or held by a dead process of this host, is taken over with a PUT ``If-Match`` on
  the ETag the taker read, so two runs racing for a dead lease cannot both win. A holder knows when it
  has lost the store, and its next commit raises (``StoreLock.check``): a renewal refused (another run
  took over), or no renewal for half the lease (the endpoint is gone: it stops writing before the
  lease can expire). Other URL protocols have no lock (``StoreLock.supported`` False): one run at a time
  is then up to the user.
"""
from __future__ import annotations

import fcntl
import json
import os
import socket
import time

from core.errors import is_disk_full
from stores.errors import StoreLockedError, StorePathError, StoreUnreachableError, store_full
from stores.objectstore import endpoint
from stores.procinfo import holder_record, pid_alive
from stores.schema import LOCK_NAME


def _path_error(store: str, what: str, e: OSError) -> StorePathError:
    return StorePathError(f"store path {store}: {what}: {e.strerror or e} (is a parent a file, or the folder "
                          f"read-only?); choose another path")


def describe(holder: dict) -> str:
    return (f"pid {holder.get('pid')} on host {holder.get('host')}, started {holder.get('started')}"
            + (f" ({holder.get('command')})" if holder.get("command") else ""))


LEASE_SECONDS = 60.0        # an S3 lease not renewed for this long (by the object store's clock) is dead
RENEW_EVERY = 1 / 3         # the holder renews every third of its lease...
GIVE_UP_AFTER = 1 / 2       # ...and stops writing when it has not managed to for half of it
RELEASE_WAIT = 10.0         # seconds a release waits for a renewal in flight


def _code(e) -> str:
    """botocore's error code of ``e`` ('' for errors without a response: no connection)."""
    return str(getattr(e, "response", {}).get("Error", {}).get("Code", ""))


class S3Lease:
    """The writer lock of a store at an ``s3://`` URL (module docstring): a lease object renewed while
    the run lives. Endpoint and credentials come from the standard AWS environment and config files
    (botocore), never from the store; messages name the URL and the holder, never a credential.

    Time is the object store's: a lease's age is the ``Date`` of the response that read it minus the
    object's ``LastModified`` (both set by the server), so the clocks of the hosts never meet (a host
    whose clock is off can neither keep a dead lease alive nor take a live one). A server without a
    ``Date`` header leaves the reader's own clock. Release deletes the lease only if it is still the
    one this run wrote (``DeleteObject`` with ``If-Match`` on its ETag); a server that does not support
    conditional deletes (``NotImplemented``) falls back to reading the ETag, then deleting, which can
    delete a lease another run took in between (AWS S3 and moto support them)."""

    def __init__(self, url: str, record: dict, lease: float = LEASE_SECONDS):
        bucket_key = url.split("://", 1)[1].rstrip("/")
        self.url = url.rstrip("/") + "/" + LOCK_NAME
        self.bucket, _, prefix = bucket_key.partition("/")
        self.key = f"{prefix}/{LOCK_NAME}" if prefix else LOCK_NAME
        self.record, self.lease = dict(record), float(lease)
        self.etag: str | None = None
        self.took_over: dict | None = None
        self.taken: str | None = None           # another run took the lease over
        self.renewed_at: float | None = None    # monotonic time of the last write of the lease
        self.renew_error: BaseException | None = None
        self._gave_up: str | None = None
        self._stop = None
        import boto3
        from botocore.config import Config
        # few, short attempts: a renewal must fail (and be tried again) well within the lease
        self.s3 = boto3.client("s3", config=Config(retries={"mode": "standard", "max_attempts": 3},
                                                   connect_timeout=5, read_timeout=10))

    def _body(self) -> bytes:
        return json.dumps({**self.record, "lease_s": self.lease}).encode()

    def _failed(self, e) -> bool:
        """Whether ``e`` is a refused conditional write (another run's lease is there)."""
        return _code(e) in ("PreconditionFailed", "412", "ConditionalRequestConflict")

    def _put(self, **cond) -> str:
        etag = self.s3.put_object(Bucket=self.bucket, Key=self.key, Body=self._body(), **cond)["ETag"]
        self.renewed_at = time.monotonic()
        return etag

    def _holder(self) -> tuple[dict | None, str | None, float]:
        """The lease there: ``(record, etag, seconds left)`` by the object store's clock (module docstring),
        ``(None, None, 0)`` when there is none."""
        try:
            r = self.s3.get_object(Bucket=self.bucket, Key=self.key)
        except self.s3.exceptions.NoSuchKey:
            return None, None, 0.0
        try:
            d = json.loads(r["Body"].read().decode())
        except ValueError:
            d = None
        d = d if isinstance(d, dict) else {}
        from email.utils import parsedate_to_datetime
        date = r.get("ResponseMetadata", {}).get("HTTPHeaders", {}).get("date")
        now = parsedate_to_datetime(date).timestamp() if date else time.time()
        age = now - r["LastModified"].timestamp()
        try:
            lease = float(d.get("lease_s", LEASE_SECONDS))
        except (TypeError, ValueError):
            lease = LEASE_SECONDS
        return d, r["ETag"], lease - age

    def acquire(self) -> "S3Lease":
        for _ in range(5):
            try:
                self.etag = self._put(IfNoneMatch="*")
                break
            except Exception as e:  # noqa: BLE001 - botocore's ClientError
                if _code(e) == "NoSuchBucket":
                    raise StorePathError(f"the bucket {self.bucket!r} of {self.url.rsplit('/', 1)[0]} does not exist "
                                         f"at {endpoint()}: create it, or choose another --out") from None
                if not self._failed(e):
                    raise
            holder, etag, left = self._holder()
            if holder is None:
                continue                        # released in between: try to create it again
            dead_here = (holder.get("host") == socket.gethostname() and holder.get("pid") != os.getpid()
                         and not pid_alive(holder.get("pid", -1), holder.get("proc_start")))
            if left > 0 and not dead_here:      # alive, or on another host and within its lease
                raise StoreLockedError(
                    f"the store {self.url.rsplit('/', 1)[0]} is in use by another dataset run: {describe(holder)}; "
                    f"its lease object {self.url} lasts {left:.0f} s more by the object store's clock and is "
                    "renewed while that run lives (wait for it to finish, or stop it)", holder=holder)
            try:                                # expired: take it over, unless another run does first
                self.etag = self._put(IfMatch=etag)
                self.took_over = holder
                break
            except Exception as e:  # noqa: BLE001
                if not self._failed(e):
                    raise
        else:
            raise StoreLockedError(f"could not take the lease {self.url}: it kept changing under this run")
        import threading
        self._stop = threading.Event()
        self._renewer = threading.Thread(target=self._renew, name="store-lease", daemon=True)
        self._renewer.start()
        return self

    def _renew(self) -> None:
        while not self._stop.wait(self.lease * RENEW_EVERY):
            try:
                self.etag = self._put(IfMatch=self.etag)
                self.renew_error = None
            except Exception as e:  # noqa: BLE001
                if self._failed(e):
                    self.taken = (f"the lease {self.url} was taken over by another run (this run did not renew "
                                  f"it within {self.lease:g} s); this run stops writing the store")
                    return
                self.renew_error = e            # no connection: try again; `lost` tells when to stop

    @property
    def lost(self) -> str | None:
        """Why this run must stop writing the store, or None: another run took the lease over, or it has
        not been renewed for ``GIVE_UP_AFTER`` of its length (the endpoint is gone), so that the run stops
        before the lease can expire and another run may take it. Once lost, always lost."""
        if self.taken:
            return self.taken
        if not self._gave_up and self.renewed_at is not None:
            since = time.monotonic() - self.renewed_at
            if since > self.lease * GIVE_UP_AFTER:
                err = self.renew_error
                self._gave_up = (f"could not renew the lease {self.url} for {since:.0f} s of its {self.lease:g} s"
                                 + (f" (last error: {type(err).__name__}: {str(err).splitlines()[0]})" if err else "")
                                 + "; this run stops writing the store before another run may take it over")
        return self._gave_up

    def release(self) -> None:
        """Delete the lease if it is still this run's. Best effort: a lease that cannot be deleted (the
        endpoint is gone) ends by itself ``lease`` seconds after its last renewal, and a run on this host
        takes over one whose process is dead at once."""
        if self._stop is not None:
            self._stop.set()
            # a renewal in flight may change the ETag (where it is not the body's MD5: SSE-KMS, SSE-C): wait
            # for it, or the conditional delete misses this run's own lease (bounded: with the endpoint gone
            # nothing can be deleted anyway)
            self._renewer.join(timeout=RELEASE_WAIT)
        etag, self.etag = self.etag, None
        if self.taken or etag is None:
            return
        try:
            self.s3.delete_object(Bucket=self.bucket, Key=self.key, IfMatch=etag)
        except Exception as e:  # noqa: BLE001
            if _code(e) not in ("NotImplemented", "501"):
                return                          # not ours any more, already gone, or no connection
            try:                                # a server without conditional deletes
                if self._holder()[1] == etag:
                    self.s3.delete_object(Bucket=self.bucket, Key=self.key)
            except Exception:  # noqa: BLE001
                pass


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
        self._make_dir()
        for _ in range(20):
            fd = self._locked_fd()
            if fd is None:
                continue                        # the file we locked was unlinked by a run releasing it
            self._check_holder(fd)
            self._write_record(fd)
            self._fd = fd
            return self
        raise StoreLockedError(f"could not take the lock {self.path}: it kept changing under this run")

    def _make_dir(self) -> None:
        if os.path.isdir(self.store):
            return
        try:
            os.makedirs(self.store, exist_ok=True)
        except OSError as e:
            if is_disk_full(e):
                raise store_full(self.store, "making its folder") from None
            raise _path_error(self.store, "cannot make the store's folder", e) from e
        self._made_dir = True

    def _locked_fd(self) -> int | None:
        """The lock file opened and ``flock``-ed (StoreLockedError while another run holds it), or None when
        the file was replaced in between (try again)."""
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
        try:
            same = os.fstat(fd).st_ino == os.stat(self.path).st_ino
        except FileNotFoundError:
            same = False
        if not same:
            os.close(fd)
            return None
        return fd

    def _check_holder(self, fd: int) -> None:
        """Refuse a record left by a run that may be alive (another host's, or a live process here); a dead
        one's is taken over (``took_over``)."""
        holder, me = self._read(fd), socket.gethostname()
        if not holder:
            return
        if holder.get("host") != me:
            os.close(fd)
            raise self._refuse(holder, f"; it runs on another host, so this one ({me}) cannot tell "
                                       "whether it is alive: if it is not, delete the lock file")
        if pid_alive(holder.get("pid", -1), holder.get("proc_start")) and holder.get("pid") != os.getpid():
            os.close(fd)
            raise self._refuse(holder, " (its process is alive but holds no lock: if it is not a "
                                       "dataset run, delete the lock file)")
        self.took_over = holder

    def _write_record(self, fd: int) -> None:
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
        """Raise if this run lost the store: StoreLockedError when another run took its S3 lease over,
        StoreUnreachableError when it could not renew the lease for half its length (``S3Lease.lost``)."""
        lost = self._lease.lost if self._lease is not None else None
        if lost:
            if self._lease.taken:
                raise StoreLockedError(lost)
            raise StoreUnreachableError(f"the object store of {self.store} at {endpoint()} could not be reached: "
                                        f"{lost}; run the same command again once it is back, and it resumes")

    def __enter__(self) -> "StoreLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()
