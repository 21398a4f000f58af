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
  keyword arguments and what every worker needs written into the job script (:func:`job_settings`),
  scaled to ``cluster.jobs`` jobs; a job SLURM could never run is refused before anything is submitted
  (``sbatch --test-only``), the run waits (saying what the queue says) for the first worker, and a job
  that ends mid-run (``scancel``, its walltime) is replaced (:class:`pipeline.jobs.JobKeeper`; the batch jobs' settings are :mod:`pipeline.jobs`).

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
import signal
import sys
import threading
from dataclasses import dataclass
from typing import Any

from distributed import LocalCluster
from distributed.diagnostics.plugin import WorkerPlugin

from pipeline.config import ClusterConfig, parse_dashboard
from pipeline.errors import ClusterError, ConfigError
from pipeline.cluster_settings import LOCALHOST, NO_DASHBOARD, PRELOAD, dashboard_bind, make_security
from core.variant import visible_gpus


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
    has_dashboard: bool = True        # False where cluster.dashboard_address is null (a cluster we start)

    @property
    def dashboard(self) -> str | None:
        if not self.has_dashboard:
            return None
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


def check_dashboard(address: str | None, where: str = "dataset.cluster.dashboard_address") -> None:
    """Refuse (ConfigError, one line) a dashboard address this machine cannot serve: bad syntax, a host
    name that does not resolve, an interface this machine does not have. A port already in use is not
    an error: distributed then serves the dashboard on another one and the run prints where."""
    import socket
    if address is None:
        return
    host, _ = parse_dashboard(dashboard_bind(address), where)
    try:
        infos = socket.getaddrinfo(host or LOCALHOST, 0, type=socket.SOCK_STREAM)
        fam, _, _, _, addr = infos[0]
        with socket.socket(fam, socket.SOCK_STREAM) as sk:
            sk.bind((addr[0], 0))
    except OSError as e:
        raise ConfigError(f"{where} {address!r} cannot be served on this machine ({e.strerror or e}); name one "
                          f"of its interfaces, e.g. 127.0.0.1:8787, or null for no dashboard") from None


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


def render_gpus(cfg: ClusterConfig) -> list[str]:
    """The GPUs a LocalCluster gives a worker each (``cluster.gpus``; :class:`ClusterConfig`)."""
    g = cfg.gpus
    if g is None or g == 0:
        return []
    have = visible_gpus()
    if g == "auto":
        return have
    if (g > len(have)) if isinstance(g, int) else any(str(x) not in have for x in g):
        raise ConfigError(f"dataset.cluster.gpus is {g!r} but this machine shows {len(have)} GPU(s) "
                          f"({', '.join(have) or 'none'}: nvidia-smi -L, within CUDA_VISIBLE_DEVICES); use 'auto', "
                          "or null for CPU workers")
    return have[:g] if isinstance(g, int) else [str(x) for x in g]


class GPULocalCluster(LocalCluster):
    """One worker process per GPU, and never two on one: the worker of GPU ``d`` has
    ``CUDA_VISIBLE_DEVICES=d`` (so drjit and torch see it as device 0) and the worker resource
    ``GPU: 1``; a replacement worker takes the GPU no other worker holds, and the cluster never grows
    past its GPUs (:meth:`scale` caps the count; a worker spec without a free GPU is refused).

    Not dask-cuda's ``LocalCUDACluster``, which does the same per-GPU setup: it needs NVML (pynvml) and
    a working driver to start, and numba; none of them is on the GPU check machine, and the CPU tests
    start this one with pretended devices. What LocalCUDACluster adds beyond it (RMM pools, UCX) the
    renderer does not use."""

    def __init__(self, gpus: list[str], **kw):
        self.gpus = list(gpus)
        super().__init__(n_workers=0, **kw)
        self.scale(len(self.gpus))

    def scale(self, n: int = 0, memory=None, cores=None):
        """Scale to ``n`` workers, at most one a GPU."""
        return super().scale(min(int(n), len(self.gpus)), memory=memory, cores=cores)

    def new_worker_spec(self):
        ((name, spec),) = super().new_worker_spec().items()
        held = {w["options"].get("env", {}).get("CUDA_VISIBLE_DEVICES") for w in self.worker_spec.values()}
        free = [g for g in self.gpus if g not in held]
        if not free:
            raise ClusterError(f"every GPU of this LocalCluster ({', '.join(self.gpus)}) has a worker already; "
                               "one worker a GPU")
        opts = dict(spec["options"])
        opts["env"] = {**opts.get("env", {}), "CUDA_VISIBLE_DEVICES": free[0]}
        opts["resources"] = {**(opts.get("resources") or {}), "GPU": 1}
        return {name: {**spec, "options": opts}}


def local_cluster(cfg: ClusterConfig, workers: int | None = None, *, say=print):
    """A LocalCluster of ``workers`` (or ``cfg.workers``, or one per core) single-purpose processes on
    127.0.0.1, its dashboard at :func:`dashboard_bind` of ``cfg.dashboard_address``; where
    :func:`render_gpus` finds GPUs, one worker per GPU instead (:class:`GPULocalCluster`)."""
    from pipeline import worker_init
    check_dashboard(cfg.dashboard_address)
    worker_init.prepare_environment()
    gpus = render_gpus(cfg)
    n = len(gpus) or workers or cfg.workers or max(1, machine_cores() // cfg.threads_per_worker)
    dash = ({"dashboard_address": NO_DASHBOARD["dashboard_address"], "scheduler_kwargs": {"dashboard": False}}
            if cfg.dashboard_address is None else {"dashboard_address": dashboard_bind(cfg.dashboard_address)})
    kw = dict(threads_per_worker=cfg.threads_per_worker, processes=True, memory_limit=cfg.memory_limit, **dash,
              host=LOCALHOST, silence_logs=logging.ERROR, preload=[PRELOAD], security=make_security(cfg.security),
              env={worker_init.LOCAL_WORKER_ENV: "1"})    # its workers leave Ctrl-C to us
    worker_init.spawn_ignoring_interrupts()
    # Ctrl-C waits until the cluster stands: one that cut LocalCluster's start short left workers half
    # started, and distributed's own close of them at exit printed an AssertionError (the chaos run)
    held = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    cluster = None
    try:
        for attempt in (1, 2):
            try:
                if not gpus:
                    cluster = LocalCluster(n_workers=n, **kw)
                else:
                    if workers or cfg.workers:
                        say(f"cluster: one worker per GPU ({n}: {', '.join(gpus)}); --workers / cluster.workers "
                            "apply to CPU workers (cluster.gpus: null for those)", flush=True)
                    cluster = GPULocalCluster(gpus, **kw)
                    cluster.wait_for_workers(n, timeout=120)
                break
            except RuntimeError as e:          # distributed: "Cluster failed to start: <cause>"
                cause = e.__cause__ or e
                if attempt == 1 and "failed to start worker process" in str(cause):
                    # a worker process died while it started (killed, out of memory): once more, then give up
                    say(f"cluster: a worker process died while the LocalCluster started ({cause}); starting it "
                        "again", flush=True)
                    continue
                raise ClusterError(f"cannot start a LocalCluster of {n} worker(s): {type(cause).__name__}: "
                                   f"{cause}") from None
    finally:
        try:
            signal.pthread_sigmask(signal.SIG_SETMASK, held)   # a Ctrl-C pressed meanwhile is raised here
        except KeyboardInterrupt:
            if cluster is not None:
                cluster.close()
            raise
    return cluster


SCHEMES = ("tcp", "tls", "ucx", "ws", "wss", "inproc")


def check_address(address: str, where: str = "--scheduler") -> str:
    """``address`` as a scheduler address ``scheme://host:port`` (``tcp://`` added to a bare
    ``host:port``); :class:`ConfigError` (exit 2, one line) for anything else."""
    from distributed.comm.addressing import parse_address, parse_host_port
    a = str(address).strip()
    full = a if "://" in a else f"tcp://{a}"
    try:
        scheme, loc = parse_address(full)
        host, port = parse_host_port(loc)
    except (ValueError, TypeError) as e:
        raise ConfigError(f"{where} {address!r} is not a scheduler address ({e}); give scheme://host:port, "
                          "e.g. tcp://head:8786") from None
    if scheme not in SCHEMES or not host or not 0 < int(port) < 65536:
        raise ConfigError(f"{where} {address!r} is not a scheduler address: give scheme://host:port with a "
                          f"scheme of {list(SCHEMES)} and a port in 1..65535, e.g. tcp://head:8786")
    return full


def probe_scheduler(address: str, timeout: float, security=None) -> None:
    """Connect to ``address`` and complete Dask's handshake within ``timeout`` seconds, else raise
    :class:`ClusterError`. ``distributed.Client``'s own timeout covers the connection but not the
    handshake: a port where something else listens (an HTTP server) hangs it for good."""
    import asyncio

    from distributed.comm import connect as comm_connect
    kw = security.get_connection_args("client") if security is not None else {}

    async def handshake():
        comm = await comm_connect(address, timeout=timeout, **kw)
        await comm.close()
    try:
        asyncio.run(asyncio.wait_for(handshake(), timeout + 1.0))
    except asyncio.TimeoutError:
        raise ClusterError(f"{address} accepts connections but does not answer as a Dask scheduler within "
                           f"{timeout + 1.0:g} s (another service on that port?); check the address") from None
    except (OSError, ValueError) as e:
        raise ClusterError(f"cannot reach the Dask scheduler at {address} within {timeout:g} s "
                           f"({type(e).__name__}: {e}); is `dask scheduler` running there?") from None


class _DashboardNoise(logging.Filter):
    """Drops a log record whose error was raised inside Bokeh's server code: the dashboard's own trouble
    with a browser tab (a websocket the tab closed while a message was on its way ends in an
    ``AssertionError`` traceback from ``bokeh.server.connection``), never the run's."""

    def filter(self, record: logging.LogRecord) -> bool:
        tb = record.exc_info[2] if record.exc_info else None
        while tb is not None:
            if f"{os.sep}bokeh{os.sep}" in tb.tb_frame.f_code.co_filename:
                return False
            tb = tb.tb_next
        return True


def quiet_dashboard() -> None:
    """Keep the terminal to the run's own lines while this process serves a dashboard (a LocalCluster's
    or a batch cluster's scheduler runs here): Bokeh's server errors, and tornado's reports of errors
    raised in Bokeh's code, are left out (distributed's logging config prints both to stderr)."""
    logging.getLogger("bokeh").setLevel(logging.CRITICAL)
    app = logging.getLogger("tornado.application")
    if not any(isinstance(f, _DashboardNoise) for f in app.filters):
        app.addFilter(_DashboardNoise())


def connect(cfg: ClusterConfig, *, scheduler: str | None = None, workers: int | None = None) -> Connection:
    """Start or reach the cluster. ``scheduler`` (the CLI's ``--scheduler``) wins over ``cfg``;
    ``workers`` overrides the local worker count or the number of batch jobs (the workers of an
    existing scheduler are not ours to size, so it is ignored there). With ``cfg.security`` the
    client speaks TLS, and an address without a scheme is taken as ``tls://``."""
    from distributed import Client
    quiet_dashboard()
    address = scheduler or (cfg.address if cfg.kind in ("scheduler", "local") else None)
    if address:
        security = make_security(cfg.security)
        if "://" not in address:
            address = f"{'tls' if security is not None else 'tcp'}://{address}"
        address = check_address(address, "--scheduler" if scheduler else "dataset.cluster.address")
        if security is not None and security.require_encryption and not address.startswith("tls://"):
            raise ConfigError(f"dataset.cluster.security requires encryption, but the scheduler address is "
                              f"{address}; use tls://{address.split('://', 1)[1]} (the scheduler started with "
                              "--tls-ca-file/--tls-cert/--tls-key), or set require_encryption: false")
        probe_scheduler(address, cfg.connect_timeout, security)
        try:
            client = Client(address, timeout=cfg.connect_timeout, set_as_default=False, security=security)
        except (OSError, TimeoutError) as e:
            raise ClusterError(f"cannot reach the Dask scheduler at {address} within {cfg.connect_timeout:g} s "
                               f"({type(e).__name__}: {e}); is `dask scheduler` running there?") from e
        return _prepared(Connection(client, None, "scheduler"))
    if cfg.kind in ("slurm", "pbs"):
        from pipeline.jobs import JobKeeper, check_job_submission, jobqueue_cluster, wait_for_jobs
        cluster = jobqueue_cluster(cfg)
        jobs = workers or cfg.jobs
        try:
            check_job_submission(cluster, cfg.kind)
            cluster.scale(jobs=jobs)
            cluster.denoise_keeper = JobKeeper(cluster, jobs)    # ended jobs are submitted again
            client = Client(cluster, set_as_default=False)
        except BaseException:
            cluster.close()
            raise
        conn = _prepared(Connection(client, cluster, cfg.kind,
                                    has_dashboard=_shows_dashboard(cluster.scheduler_spec["options"])))
        try:
            wait_for_jobs(conn, jobs)          # jobqueue workers come late: the first one, or a clear error
        except BaseException:
            conn.close()
            raise
        return conn
    try:
        cluster = local_cluster(cfg, workers)
    except (OSError, TimeoutError) as e:
        raise ClusterError(f"cannot start a LocalCluster: {e}") from e
    client = Client(cluster, set_as_default=False)
    return _prepared(Connection(client, cluster, "local", has_dashboard=cfg.dashboard_address is not None))


def _shows_dashboard(opts: dict) -> bool:
    """Whether a scheduler started with ``opts`` serves a dashboard (``Scheduler``'s own rule)."""
    dashboard = opts.get("dashboard")
    return bool(dashboard or (dashboard is None and opts.get("dashboard_address")))


def _prepared(conn: Connection) -> Connection:
    try:
        install_worker_init(conn.client)
    except ClusterError:
        conn.close()
        raise
    return conn
