"""Where the graph runs: a LocalCluster sized to the machine, an existing scheduler, or a batch cluster.

:func:`connect` returns a :class:`Connection` (``client``, ``cluster`` or None, ``dashboard``) and
fails fast with :class:`ClusterError` (exit code 2 through ``python -m pipeline``) when the scheduler
cannot be reached or dask-jobqueue is missing, before anything is rendered.

- ``local``: ``LocalCluster(n_workers=workers or cores, threads_per_worker=1, processes=True)``; each
  rendering task sizes drjit's thread pool to its worker's threads (``pipeline.tasks``), so
  2 workers on 2 cores do not oversubscribe (NOTES.md: 1.85x over one worker).
- ``scheduler`` (or ``--scheduler ADDR``): ``Client(ADDR)``; start workers yourself with
  ``dask worker ADDR --nthreads 1`` on machines that see the store.
- ``slurm`` / ``pbs``: ``dask_jobqueue.SLURMCluster`` / ``PBSCluster`` with ``cluster.jobqueue`` as
  keyword arguments, scaled to ``cluster.jobs`` jobs.
"""
from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from typing import Any

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
        return Connection(client, None, "scheduler")
    if cfg.kind in ("slurm", "pbs"):
        cluster = jobqueue_cluster(cfg)
        cluster.scale(jobs=workers or cfg.jobs)
        client = Client(cluster, set_as_default=False)
        return Connection(client, cluster, cfg.kind)
    try:
        cluster = local_cluster(cfg, workers)
    except (OSError, TimeoutError) as e:
        raise ClusterError(f"cannot start a LocalCluster: {e}") from e
    client = Client(cluster, set_as_default=False)
    return Connection(client, cluster, "local")
