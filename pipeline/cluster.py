"""Where the graph runs: a LocalCluster sized to the machine, an existing scheduler, or a batch cluster.

:func:`connect` returns a :class:`Connection` (``client``, ``cluster`` or None, ``dashboard``) and
fails fast with :class:`ClusterError` (exit code 2 through ``python -m pipeline``) when the scheduler
cannot be reached or dask-jobqueue is missing, before anything is rendered.

- ``local``: ``LocalCluster(n_workers=workers or cores, threads_per_worker=1, processes=True)``; each
  rendering task sizes drjit's thread pool to its worker's threads (``pipeline.tasks``), so
  2 workers on 2 cores do not oversubscribe (NOTES.md: 1.85x over one worker).
- ``scheduler`` (or ``--scheduler ADDR``): ``Client(ADDR)``; start workers yourself with
  ``dask worker ADDR --nthreads 1`` on machines that see the store (no ``--preload`` needed).
- ``slurm`` / ``pbs``: ``dask_jobqueue.SLURMCluster`` / ``PBSCluster`` with ``cluster.jobqueue`` as
  keyword arguments, scaled to ``cluster.jobs`` jobs.

Whatever the kind, :func:`connect` registers :class:`WorkerInit` (a distributed ``WorkerPlugin``) with
``client.register_plugin``: every current worker and every worker that joins later runs its ``setup``
before it gets a task, and that imports pymeshlab in the worker's main thread (see
``pipeline.worker_init``). ``setup`` is a coroutine, so the worker runs it on its event loop, which in
a ``dask worker`` process (nanny or not) and in a LocalCluster worker process is the main thread.
"""
from __future__ import annotations

import logging
import os
import sys
import threading
from dataclasses import dataclass
from typing import Any

from distributed.diagnostics.plugin import WorkerPlugin

from pipeline.config import ClusterConfig
from pipeline.errors import PipelineError


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
    """A LocalCluster of ``workers`` (or ``cfg.workers``, or one per core) single-purpose processes."""
    from distributed import LocalCluster
    from pipeline import worker_init
    worker_init.prepare_environment()
    n = workers or cfg.workers or max(1, machine_cores() // cfg.threads_per_worker)
    return LocalCluster(n_workers=n, threads_per_worker=cfg.threads_per_worker, processes=True,
                        memory_limit=cfg.memory_limit, dashboard_address=cfg.dashboard_address,
                        host="127.0.0.1", silence_logs=logging.ERROR, preload=[PRELOAD])


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
        kw.setdefault("scheduler_options", {"dashboard_address": cfg.dashboard_address})
    try:
        return cls(**kw)
    except TypeError as e:
        raise ClusterError(f"cluster.jobqueue: {e}") from e


def connect(cfg: ClusterConfig, *, scheduler: str | None = None, workers: int | None = None) -> Connection:
    """Start or reach the cluster. ``scheduler`` (the CLI's ``--scheduler``) wins over ``cfg``;
    ``workers`` overrides the local worker count or the number of batch jobs."""
    from distributed import Client
    address = scheduler or (cfg.address if cfg.kind in ("scheduler", "local") else None)
    if address:
        if "://" not in address:
            address = f"tcp://{address}"
        try:
            client = Client(address, timeout=cfg.connect_timeout, set_as_default=False)
        except (OSError, TimeoutError) as e:
            raise ClusterError(f"cannot reach the Dask scheduler at {address} within {cfg.connect_timeout:g} s "
                               f"({type(e).__name__}: {e}); is `dask scheduler` running there?") from e
        if workers:
            pass    # the workers of an existing scheduler are not ours to size
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
