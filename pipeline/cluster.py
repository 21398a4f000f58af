"""Where the graph runs: a LocalCluster sized to the machine, an existing scheduler, or a batch cluster.

:func:`connect` returns a :class:`Connection` (``client``, ``cluster`` or None, ``dashboard``) and
fails fast with :class:`ClusterError` (exit code 2 through ``python -m pipeline``) when the scheduler
cannot be reached or dask-jobqueue is missing, before anything is rendered.

- ``local``: ``LocalCluster(n_workers=workers or cores, threads_per_worker=1, processes=True)`` on
  127.0.0.1; each rendering task sizes drjit's thread pool to its worker's threads
  (``pipeline.tasks``), so 2 workers on 2 cores do not oversubscribe (``make bench`` measures 2
  workers against 1).
- ``scheduler`` (or ``--scheduler ADDR``): ``Client(ADDR)``; start workers yourself with
  ``dask worker ADDR --nthreads 1`` on machines that see the store (no ``--preload`` needed).
- ``slurm`` / ``pbs``: ``dask_jobqueue.SLURMCluster`` / ``PBSCluster`` with ``cluster.jobqueue`` as
  keyword arguments, scaled to ``cluster.jobs`` jobs.

The dashboard listens on ``cluster.dashboard_address``; an address without a host (``:8787``, which
distributed would open on every interface) is bound to 127.0.0.1 (:func:`dashboard_bind`): reach it
from elsewhere through an SSH tunnel, or name the interface (``0.0.0.0:8787``) to open it.
``cluster.security`` (:func:`make_security`) turns into a ``distributed.security.Security`` (TLS)
used by the client, and by the LocalCluster or batch cluster it starts.

Whatever the kind, :func:`connect` registers :class:`WorkerInit` (a distributed ``WorkerPlugin``) with
``client.register_plugin``: every current worker and every worker that joins later runs its ``setup``
before it gets a task, and that imports pymeshlab in the worker's main thread (see
``pipeline.worker_init``). ``setup`` is a coroutine, so the worker runs it on its event loop, which in
a ``dask worker`` process (nanny or not) and in a LocalCluster worker process is the main thread.
"""
from __future__ import annotations

import logging
import os
import ssl
import sys
import threading
from dataclasses import dataclass
from typing import Any

from distributed.diagnostics.plugin import WorkerPlugin

from pipeline.config import ClusterConfig
from pipeline.errors import ConfigError, PipelineError


class ClusterError(PipelineError, ConnectionError):
    """The Dask cluster cannot be started or reached."""


def machine_cores() -> int:
    """CPU cores this process may use (affinity mask, else ``os.cpu_count()``)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


@dataclass
class Connection:
    client: Any
    cluster: Any | None
    kind: str

    @property
    def dashboard(self) -> str | None:
        try:
            return self.client.dashboard_link
        except Exception:  # noqa: BLE001 - no dashboard (bokeh missing, disabled)
            return None

    @property
    def address(self) -> str:
        return self.client.scheduler.address

    def n_workers(self) -> int:
        return len(self.client.scheduler_info(n_workers=-1).get("workers", {}))

    def close(self) -> None:
        for obj in (self.client, self.cluster):
            if obj is None:
                continue
            try:
                obj.close()
            except Exception:  # noqa: BLE001 - closing after Ctrl-C or a lost scheduler
                pass


LOCALHOST = "127.0.0.1"
# cluster.security keys: distributed.security.Security's settings that a YAML file can hold
SECURITY_FILES = ("tls_ca_file", "tls_client_cert", "tls_client_key", "tls_scheduler_cert",
                  "tls_scheduler_key", "tls_worker_cert", "tls_worker_key")
SECURITY_KEYS = ("require_encryption", *SECURITY_FILES, "tls_ciphers", "tls_min_version", "tls_max_version")
TLS_VERSIONS = ("TLSv1_2", "TLSv1_3")


def dashboard_bind(address: str | None) -> str | None:
    """``cluster.dashboard_address`` as bound: one without a host (``:8787``, ``8787``) on 127.0.0.1,
    so the dashboard is not open to the network unless an interface is named (``0.0.0.0:8787``)."""
    if address is None:
        return None
    a = str(address).strip()
    if a.startswith(":") or a.isdigit():
        return f"{LOCALHOST}:{a.lstrip(':')}"
    return a


def check_security(sec, where: str = "dataset.cluster.security") -> None:
    """Check the shape of ``cluster.security`` (no file is opened): a mapping of ``SECURITY_KEYS`` with
    ``tls_ca_file`` and ``tls_client_cert`` set. Raises :class:`ConfigError` naming the key."""
    if not isinstance(sec, dict):
        raise ConfigError(f"{where} must be a mapping of distributed TLS settings ({', '.join(SECURITY_KEYS)}), "
                          f"got {sec!r}")
    unknown = sorted(set(map(str, sec)) - set(SECURITY_KEYS))
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {unknown}; known: {list(SECURITY_KEYS)}")
    for k in SECURITY_FILES + ("tls_ciphers",):
        v = sec.get(k)
        if v is not None and not (isinstance(v, str) and v.strip()):
            raise ConfigError(f"{where}.{k} must be a file path (a string), got {v!r}")
    for k in ("tls_ca_file", "tls_client_cert"):
        if not sec.get(k):
            raise ConfigError(f"{where}.{k} must be set: a shared scheduler speaks mutual TLS, so the client "
                              "needs the CA certificate (tls_ca_file) and its own certificate (tls_client_cert, "
                              "plus tls_client_key unless the key is in that file)")
    r = sec.get("require_encryption")
    if r is not None and not isinstance(r, bool):
        raise ConfigError(f"{where}.require_encryption must be true or false, got {r!r}")
    for k in ("tls_min_version", "tls_max_version"):
        v = sec.get(k)
        if v is not None and v not in TLS_VERSIONS:
            raise ConfigError(f"{where}.{k} must be one of {list(TLS_VERSIONS)}, got {v!r}")


def make_security(sec, where: str = "dataset.cluster.security"):
    """``cluster.security`` -> ``distributed.security.Security`` (None when not set). Paths may use
    ``~`` and ``$VARS``; each must name a readable file on this machine. ``require_encryption``
    defaults to true: every connection is TLS, a ``tcp://`` address is refused."""
    if sec is None:
        return None
    check_security(sec, where)
    from distributed.security import Security
    kw = {"require_encryption": sec.get("require_encryption", True)}
    for k in SECURITY_FILES:
        if sec.get(k):
            path = os.path.expandvars(os.path.expanduser(sec[k]))
            if not os.path.isfile(path) or not os.access(path, os.R_OK):
                raise ConfigError(f"{where}.{k}: cannot read {path!r} (no such file, or not readable); give the "
                                  "path of the PEM file on this machine")
            kw[k] = path
    if sec.get("tls_ciphers"):
        kw["tls_ciphers"] = sec["tls_ciphers"]
    for k in ("tls_min_version", "tls_max_version"):
        if sec.get(k):
            kw[k] = ssl.TLSVersion[sec[k]]
    return Security(**kw)


PRELOAD = "pipeline.worker_init"   # every worker imports it first (see that module); `dask worker --preload`
PLUGIN_NAME = "denoise-worker-init"
log = logging.getLogger(__name__)


class WorkerInit(WorkerPlugin):
    """What every worker needs before its first task (``pipeline.worker_init``): pymeshlab imported in
    its main thread, drjit's libLLVM found, BLAS/OpenMP pools of one thread. Registered by
    :func:`connect` on every kind of cluster, so workers started with a plain ``dask worker`` need no
    ``--preload``. ``worker.denoise_init`` records what ``setup`` found (thread, main or not)."""

    idempotent = True
    name = PLUGIN_NAME

    async def setup(self, worker):            # a coroutine: the worker awaits it on its event loop
        main = threading.current_thread() is threading.main_thread()
        had = "pymeshlab" in sys.modules
        if main:
            from pipeline import worker_init      # imports pymeshlab here, in the main thread
            worker_init.prepare_environment()
        elif not had:
            # A worker whose event loop is not its process's main thread (an in-process, threaded
            # LocalCluster): importing here would corrupt the heap, so leave it; a mesh task then
            # refuses with scene_gen.meshes' clear error instead of crashing.
            log.warning("worker %s: event loop not in the main thread; pymeshlab not imported", worker.address)
        worker.denoise_init = {"thread": threading.current_thread().name, "main_thread": main,
                               "pymeshlab": "pymeshlab" in sys.modules, "had_pymeshlab": had}


def install_worker_init(client) -> None:
    """Register :class:`WorkerInit` on ``client``'s cluster (current and future workers)."""
    try:
        client.register_plugin(WorkerInit(), name=PLUGIN_NAME)
    except Exception as e:  # noqa: BLE001 - a worker's setup failed: say which, before anything runs
        raise ClusterError(f"cannot prepare the Dask workers (pipeline.cluster.WorkerInit): "
                           f"{type(e).__name__}: {e}") from e


def local_cluster(cfg: ClusterConfig, workers: int | None = None):
    """A LocalCluster of ``workers`` (or ``cfg.workers``, or one per core) single-purpose processes on
    127.0.0.1, its dashboard at :func:`dashboard_bind` of ``cfg.dashboard_address``."""
    from distributed import LocalCluster
    from pipeline import worker_init
    worker_init.prepare_environment()
    n = workers or cfg.workers or max(1, machine_cores() // cfg.threads_per_worker)
    return LocalCluster(n_workers=n, threads_per_worker=cfg.threads_per_worker, processes=True,
                        memory_limit=cfg.memory_limit, dashboard_address=dashboard_bind(cfg.dashboard_address),
                        host=LOCALHOST, silence_logs=logging.ERROR, preload=[PRELOAD],
                        security=make_security(cfg.security))


def jobqueue_cluster(cfg: ClusterConfig):
    """A dask-jobqueue SLURMCluster/PBSCluster from ``cfg.jobqueue`` (not yet scaled)."""
    try:
        import dask_jobqueue
    except ImportError as e:
        raise ClusterError(f"cluster.kind {cfg.kind!r} needs dask-jobqueue: pip install 'dask-jobqueue>=0.8' "
                           "(or pip install -e .[cluster])") from e
    cls = {"slurm": dask_jobqueue.SLURMCluster, "pbs": dask_jobqueue.PBSCluster}[cfg.kind]
    kw = dict(cfg.jobqueue)
    extra = list(kw.get("worker_extra_args") or [])
    if PRELOAD not in extra:
        kw["worker_extra_args"] = extra + ["--preload", PRELOAD]
    if cfg.dashboard_address is not None:
        kw.setdefault("scheduler_options", {"dashboard_address": dashboard_bind(cfg.dashboard_address)})
    security = make_security(cfg.security)
    if security is not None:
        kw.setdefault("security", security)
    try:
        return cls(**kw)
    except TypeError as e:
        raise ClusterError(f"cluster.jobqueue: {e}") from e


def connect(cfg: ClusterConfig, *, scheduler: str | None = None, workers: int | None = None) -> Connection:
    """Start or reach the cluster. ``scheduler`` (the CLI's ``--scheduler``) wins over ``cfg``;
    ``workers`` overrides the local worker count or the number of batch jobs (the workers of an
    existing scheduler are not ours to size, so it is ignored there). With ``cfg.security`` the
    client speaks TLS, and an address without a scheme is taken as ``tls://``."""
    from distributed import Client
    address = scheduler or (cfg.address if cfg.kind in ("scheduler", "local") else None)
    if address:
        security = make_security(cfg.security)
        if "://" not in address:
            address = f"{'tls' if security is not None else 'tcp'}://{address}"
        if security is not None and security.require_encryption and not address.startswith("tls://"):
            raise ConfigError(f"dataset.cluster.security requires encryption, but the scheduler address is "
                              f"{address}; use tls://{address.split('://', 1)[1]} (the scheduler started with "
                              "--tls-ca-file/--tls-cert/--tls-key), or set require_encryption: false")
        try:
            client = Client(address, timeout=cfg.connect_timeout, set_as_default=False, security=security)
        except (OSError, TimeoutError) as e:
            raise ClusterError(f"cannot reach the Dask scheduler at {address} within {cfg.connect_timeout:g} s "
                               f"({type(e).__name__}: {e}); is `dask scheduler` running there?") from e
        return _prepared(Connection(client, None, "scheduler"))
    if cfg.kind in ("slurm", "pbs"):
        cluster = jobqueue_cluster(cfg)
        cluster.scale(jobs=workers or cfg.jobs)
        client = Client(cluster, set_as_default=False)
        return _prepared(Connection(client, cluster, cfg.kind))
    try:
        cluster = local_cluster(cfg, workers)
    except (OSError, TimeoutError) as e:
        raise ClusterError(f"cannot start a LocalCluster: {e}") from e
    client = Client(cluster, set_as_default=False)
    return _prepared(Connection(client, cluster, "local"))


def _prepared(conn: Connection) -> Connection:
    try:
        install_worker_init(conn.client)
    except ClusterError:
        conn.close()
        raise
    return conn
