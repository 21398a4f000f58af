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
  that ends mid-run (``scancel``, its walltime) is replaced (:class:`JobKeeper`).

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
import ssl
import sys
import threading
from dataclasses import dataclass
from typing import Any

from distributed import LocalCluster
from distributed.diagnostics.plugin import WorkerPlugin

from pipeline.config import SECURITY_FILES, ClusterConfig, check_security, parse_dashboard
from pipeline.errors import ConfigError, PipelineError
from core.checks import is_int, is_number, need
from core.variant import visible_gpus


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


LOCALHOST = "127.0.0.1"
# A scheduler always serves its HTTP routes (/health, /metrics), dashboard or not, and distributed puts
# them on 8787 unless told otherwise: with ``dashboard_address: null`` they go to a free local port, so a
# run without a dashboard never takes the port of another run's dashboard.
NO_DASHBOARD = {"dashboard": False, "dashboard_address": f"{LOCALHOST}:0"}


def dashboard_bind(address: str | None) -> str | None:
    """``cluster.dashboard_address`` as bound: one without a host (``:8787``, ``8787``) on 127.0.0.1,
    so the dashboard is not open to the network unless an interface is named (``0.0.0.0:8787``)."""
    if address is None:
        return None
    a = str(address).strip()
    if a.startswith(":") or a.isdigit():
        return f"{LOCALHOST}:{a.lstrip(':')}"
    return a


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


def jobqueue_cluster(cfg: ClusterConfig):
    """A dask-jobqueue SLURMCluster/PBSCluster from ``cfg.jobqueue`` with what every worker needs
    (:func:`job_settings`), not yet scaled. ``cluster.job_script()`` shows the job script it submits."""
    try:
        import dask_jobqueue
    except ImportError as e:
        raise ClusterError(f"cluster.kind {cfg.kind!r} needs dask-jobqueue: pip install 'dask-jobqueue>=0.8' "
                           "(or pip install -e .[cluster])") from e
    cls = {"slurm": dask_jobqueue.SLURMCluster, "pbs": dask_jobqueue.PBSCluster}[cfg.kind]
    kw = job_settings(cfg)
    security = make_security(cfg.security)
    if security is not None:
        kw.setdefault("security", security)
    try:
        return cls(**kw)
    except (TypeError, ValueError) as e:
        raise ClusterError(f"dataset.cluster.jobqueue: {type(e).__name__}: {e}") from e


JOB_THREAD_ENV = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")   # as pipeline.worker_init sets them
JOB_PASS_ENV = ("MI_VARIANT", "DENOISE_FORCE_CPU")     # this machine's choice of variant, passed on when set


def job_settings(cfg: ClusterConfig) -> dict:
    """The keyword arguments of the SLURMCluster / PBSCluster: ``cfg.jobqueue`` with what every worker needs
    written into its job script, so a job does not depend on what sbatch or qsub pass on from here:

    - threads: ``processes`` (workers a job) defaults to ``cores / cluster.threads_per_worker``, one
      single-threaded worker a core by default; when given, ``cores`` must be ``processes x
      threads_per_worker`` (dask-jobqueue gives each worker cores / processes threads, and the render
      tasks size drjit's pool to a worker's threads); ``job_cpu`` may not be below ``cores``;
    - ``memory`` (the job's, shared by its workers) must be a size;
    - ``python`` defaults to this interpreter (this checkout's venv); a relative path such as
      ``.venv/bin/python`` is taken from the checkout (:func:`job_python`), not from where a job starts;
    - ``resources: {GPU: 1}`` (our key, not dask-jobqueue's) becomes ``--resources GPU=1`` on the worker
      command line: what ``tasks.reference_resources`` asks for; and ``--preload pipeline.worker_init``;
    - ``gpus_per_job: G`` (ours too; G must equal ``processes``): SLURM's ``--gres=gpu:G`` (unless the
      directives ask for GPUs already, and refused where they ask for fewer; PBS: ask in ``resource_spec``),
      ``GPU: 1`` for every worker, and each of a job's workers keeps one of the job's GPUs
      (``worker_init.gpu_for_worker``); ``resources: {GPU: ...}`` for several workers of a job without it
      is refused (they would share a GPU);
    - the job script's prologue (``job_script_prologue``): ``cd`` to this directory (PBS starts jobs
      in $HOME; a relative ``--out`` must name the same store for the workers), BLAS/OpenMP pools of one
      thread, glibc's allocator thresholds (``worker_init.MALLOC_ENV``), drjit's libLLVM
      (``DRJIT_LIBLLVM_PATH``, exported where that file exists on the node),
      ``MI_VARIANT`` / ``DENOISE_FORCE_CPU`` when set here; then the config's own prologue lines, which
      may override any of them;
    - the dashboard at :func:`dashboard_bind` of ``cluster.dashboard_address`` (none when null) unless
      ``scheduler_options`` names one.

    Raises ConfigError (exit 2) naming the setting."""
    kw = dict(cfg.jobqueue)
    _job_threads(kw, cfg.threads_per_worker)
    _job_memory(kw)
    kw["python"] = job_python(kw.get("python") or sys.executable)
    logs = kw.get("log_directory")
    if isinstance(logs, str) and logs and not logs.startswith(("$", "~")):
        kw["log_directory"] = os.path.abspath(logs)     # the #SBATCH -o/-e paths, whatever the job's directory
    extra_env = _job_workers(kw, cfg.kind)
    kw["job_script_prologue"] = _job_prologue(kw, extra_env)
    opts = kw.get("scheduler_options") or {}
    need(isinstance(opts, dict), f"{JOBQUEUE}.scheduler_options", "a mapping of Scheduler arguments", opts,
         ConfigError)
    opts = dict(opts)
    if "dashboard_address" not in opts and "dashboard" not in opts:
        if cfg.dashboard_address is None:
            opts.update(NO_DASHBOARD)
        else:
            opts["dashboard_address"] = dashboard_bind(cfg.dashboard_address)
    kw["scheduler_options"] = opts
    return kw


JOBQUEUE = "dataset.cluster.jobqueue"     # where the settings live, in messages


def _job_threads(kw: dict, tpw: int) -> None:
    """``cores``, ``processes`` (default ``cores / threads_per_worker``) and ``job_cpu`` of a job, checked."""
    cores, procs = kw.get("cores"), kw.get("processes")
    need(is_int(cores) and cores >= 1, f"{JOBQUEUE}.cores", "an integer >= 1 (the CPUs one job asks for)", cores,
         ConfigError)
    if procs is None:
        if cores % tpw:
            raise ConfigError(f"{JOBQUEUE}.cores ({cores}) must be a multiple of dataset.cluster.threads_per_worker "
                              f"({tpw}): a job runs cores / threads_per_worker workers")
        kw["processes"] = procs = cores // tpw
    else:
        need(is_int(procs) and procs >= 1, f"{JOBQUEUE}.processes", "an integer >= 1 (Dask workers a job)", procs,
             ConfigError)
    if procs * tpw != cores:
        fixes = [f"processes: {cores // tpw}"] if cores % tpw == 0 else []
        fixes += [f"dataset.cluster.threads_per_worker: {cores // procs}"] if cores % procs == 0 else []
        raise ConfigError(f"{JOBQUEUE}: cores ({cores}) must equal processes ({procs}) x "
                          f"dataset.cluster.threads_per_worker ({tpw}): each of a job's workers gets cores / "
                          "processes threads and drjit renders "
                          f"with a worker's threads; set {' or '.join(fixes) or 'them to agree'}")
    job_cpu = kw.get("job_cpu")
    need(job_cpu is None or (is_int(job_cpu) and job_cpu >= cores), f"{JOBQUEUE}.job_cpu",
         f"null (= cores) or an integer >= cores ({cores}): the job's workers run {cores} threads", job_cpu,
         ConfigError)


def _job_memory(kw: dict) -> None:
    from dask.utils import parse_bytes
    mem = kw.get("memory")
    try:
        if isinstance(mem, bool) or int(parse_bytes(str(mem))) <= 0:
            raise ValueError(mem)
    except (ValueError, TypeError):
        raise ConfigError(f"{JOBQUEUE}.memory must be a size like '4GiB' (the memory one job asks for, shared by "
                          f"its {kw['processes']} worker(s)), got {mem!r}") from None


def _job_workers(kw: dict, kind: str) -> list[str]:
    """The workers' command line (``worker_extra_args``: resources, ``gpus_per_job``, the preload) and the
    environment lines that go with it (a GPU job's workers split its GPUs)."""
    from pipeline import worker_init
    extra = kw.get("worker_extra_args") or []
    need(isinstance(extra, list), f"{JOBQUEUE}.worker_extra_args", "a list of `dask worker` arguments", extra,
         ConfigError)
    extra = [str(a) for a in extra]
    res, gpus, extra_env = kw.pop("resources", None), kw.pop("gpus_per_job", None), []
    if gpus is not None:
        if not (is_int(gpus) and gpus >= 1) or gpus != kw["processes"]:
            raise ConfigError(f"{JOBQUEUE}.gpus_per_job must be an integer >= 1 equal to the job's workers "
                              f"(processes: {kw['processes']}; one worker per GPU), got {gpus!r}; set processes "
                              "and cores to match")
        asked = _gpus_asked(kw, kind)
        if asked is not None and asked < gpus:
            raise ConfigError(f"{JOBQUEUE}: the job asks the batch system for {asked} GPU(s) but gpus_per_job is "
                              f"{gpus}: its {gpus} workers would share them (one worker per GPU); ask for {gpus}")
        if kind == "slurm":
            dirs = [str(d) for d in kw.get("job_extra_directives") or []]
            if not any(d.startswith(("--gres=gpu", "--gpus")) for d in dirs):
                kw["job_extra_directives"] = dirs + [f"--gres=gpu:{gpus}"]
        res = {**(res or {}), "GPU": 1}
        extra_env = [f"export {worker_init.GPU_SPLIT_ENV}={gpus}"]
    elif kw["processes"] > 1 and ((isinstance(res, dict) and "GPU" in res) or _extra_gpu(extra)):
        raise ConfigError(f"{JOBQUEUE}.resources gives each of a job's {kw['processes']} workers a GPU, but nothing "
                          f"gives each its own: they would share one. Set gpus_per_job: {kw['processes']} (a GPU a "
                          "worker), or processes: 1")
    if res is not None:
        need(isinstance(res, dict) and res and all(
            isinstance(k, str) and k.strip() and "=" not in k and "," not in k and " " not in k
            and is_number(v) and v > 0 for k, v in res.items()), f"{JOBQUEUE}.resources",
            "a mapping of resource names to the amount each worker has, e.g. {GPU: 1}", res, ConfigError)
        if "--resources" in extra:
            raise ConfigError(f"{JOBQUEUE}: worker resources are given twice, as resources and as --resources in "
                              "worker_extra_args; keep one")
        extra += ["--resources", ",".join(f"{k}={v}" for k, v in res.items())]
    if PRELOAD not in extra:
        extra += ["--preload", PRELOAD]
    kw["worker_extra_args"] = extra
    return extra_env


def _extra_gpu(extra: list[str]) -> bool:
    """Whether ``worker_extra_args`` give the workers a ``GPU`` resource (``--resources GPU=1,...``)."""
    return any(a == "--resources" and i + 1 < len(extra) and any(
        r.split("=", 1)[0].strip() == "GPU" for r in extra[i + 1].split(",")) for i, a in enumerate(extra))


def _gpus_asked(kw: dict, kind: str) -> int | None:
    """The GPUs a job asks its batch system for in the config's own words: SLURM's ``--gres=gpu[:type]:N``,
    ``--gpus[-per-node]=[type:]N`` directives, PBS's ``ngpus=N`` in ``resource_spec``; None where it names
    none (or in words this cannot read)."""
    import re
    if kind == "slurm":
        text = " ".join(str(d) for d in kw.get("job_extra_directives") or [])
        m = re.search(r"--gres=gpu(?::[\w.-]+)*?(?::(\d+))?(?:[,\s]|$)|--gpus(?:-per-node)?=(?:[\w.-]+:)?(\d+)", text)
        if m is None:
            return None
        return int(m.group(1) or m.group(2) or 1)
    m = re.search(r"\bngpus=(\d+)", str(kw.get("resource_spec") or ""))
    return int(m.group(1)) if m else None


def _job_prologue(kw: dict, extra_env: list[str]) -> list[str]:
    """The job script's first lines (``job_settings``' docstring), then the config's own."""
    import shlex

    from core.errors import VariantError
    from core.variant import find_libllvm
    from pipeline import worker_init
    lines = [f"cd {shlex.quote(os.getcwd())}"]
    lines += [f"export {k}=1" for k in JOB_THREAD_ENV]
    lines += [f"export {k}={shlex.quote(os.environ.get(k) or v)}" for k, v in worker_init.MALLOC_ENV.items()]
    try:
        lib = find_libllvm()
    except VariantError:
        lib = None
    if lib:
        q = shlex.quote(os.path.abspath(lib))
        lines.append(f"if [ -f {q} ]; then export DRJIT_LIBLLVM_PATH={q}; fi")
    lines += [f"export {k}={shlex.quote(os.environ[k])}" for k in JOB_PASS_ENV if os.environ.get(k)]
    lines += extra_env
    user = kw.pop("job_script_prologue", None) or kw.pop("env_extra", None) or []
    kw.pop("env_extra", None)
    if isinstance(user, str):
        user = [user]
    need(isinstance(user, list), f"{JOBQUEUE}.job_script_prologue", "a list of shell lines", user, ConfigError)
    return lines + [str(x) for x in user]


def job_python(python: str) -> str:
    """The worker jobs' ``python``: a relative path (``.venv/bin/python``) made absolute against this
    checkout, where ``make setup`` puts the venv (else against the current directory), so it means the
    same wherever a job starts; an absolute path, a bare name (found on the node's PATH) and one starting
    with ``$`` or ``~`` (expanded by the job's shell) are kept. Links are not followed: a venv's python
    is one, and resolving it would leave the venv."""
    from pathlib import Path
    p = str(python)
    if os.path.isabs(p) or "/" not in p or p.startswith(("$", "~")):
        return p
    root = Path(__file__).resolve().parent.parent
    return os.path.abspath(root / p) if os.path.lexists(root / p) else os.path.abspath(p)


def check_job_submission(cluster, kind: str, timeout: float = 60.0) -> None:
    """Ask the batch system whether it would ever run one worker job, before any is submitted: SLURM's
    ``sbatch --test-only`` on the job script. A job asking for more CPUs or memory than a node of the
    partition has is otherwise accepted and waits in the queue for ever (reason ``PartitionConfig``),
    or refused with the run waiting for workers that never come. Raises ClusterError with sbatch's
    answer and the job's request. PBS has no such check: nothing is done."""
    import shutil
    import subprocess
    import tempfile
    if kind != "slurm":
        return
    if shutil.which("sbatch") is None:
        raise ClusterError("cluster.kind 'slurm' needs SLURM's sbatch on this machine's PATH: run from a login node "
                           "of the cluster (for a one-node cluster on this machine: scripts/local-slurm.sh up)")
    with tempfile.NamedTemporaryFile("w", suffix=".sh", prefix="denoise-job-") as f:
        f.write(cluster.job_script())
        f.flush()
        try:
            r = subprocess.run(["sbatch", "--test-only", f.name], capture_output=True, text=True, timeout=timeout)
        except subprocess.TimeoutExpired:
            raise ClusterError(f"sbatch --test-only did not answer within {timeout:g} s: is slurmctld up "
                               "(sinfo)?") from None
    if r.returncode != 0:
        said = " | ".join(ln.strip() for ln in (r.stderr + r.stdout).splitlines() if ln.strip())
        raise ClusterError(f"SLURM would never run the worker job that dataset.cluster.jobqueue describes "
                           f"({job_request(cluster)}): sbatch --test-only says: {said or f'exit {r.returncode}'}; "
                           "ask for at most what a node of the partition has (sinfo -N -o '%N %c %m %P')")


def job_request(cluster) -> str:
    """What a worker job asks the batch system for: its ``#SBATCH`` / ``#PBS`` directives, one line."""
    heads = [ln.split(None, 1)[1] for ln in cluster.job_header.splitlines()
             if ln.startswith(("#SBATCH ", "#PBS ")) and len(ln.split(None, 1)) == 2]
    return " ".join(h for h in heads if not h.startswith(("-J", "-e", "-o", "-N")))


JOB_GONE_GRACE = 5.0          # seconds a job's workers may be away before the job counts as ended
JOB_WAIT_NOTE = 30.0          # seconds between notes while no worker job has started
JOB_SUBMIT_TIMEOUT = 120.0    # seconds the first submission may take
# squeue reasons of a pending job that will never start
HOPELESS = ("PartitionConfig", "PartitionNodeLimit", "PartitionTimeLimit", "BadConstraints", "InvalidAccount",
            "InvalidQOS", "DependencyNeverSatisfied")


def _join_log_class():
    from distributed.diagnostics.plugin import SchedulerPlugin

    class JoinLog(SchedulerPlugin):
        """The names of every worker that has joined the scheduler: a worker may join and leave between
        two looks at who is there (a job cancelled, killed or out of memory right after its start)."""
        name = "denoise-join-log"

        def __init__(self, on_join=None):
            self.names: set = set()
            self.on_join = on_join

        async def start(self, scheduler):
            self.names |= {str(ws.name) for ws in scheduler.workers.values()}

        def add_worker(self, scheduler, worker):
            ws = scheduler.workers.get(worker)
            if ws is not None:
                self.names.add(str(ws.name))
                if self.on_join is not None:
                    self.on_join(str(ws.name))
    return JoinLog


class JobKeeper:
    """Keep ``jobs`` worker jobs in the queue for the whole run. dask-jobqueue submits a job once: one
    that ends (``scancel``, its walltime, a lost node, a worker's ``--lifetime``) is not submitted again
    (``SpecCluster`` re-creates workers only when scaled, and ``adapt`` at a fixed size sees its plan
    unchanged). So every ``every`` seconds, on the cluster's event loop: a job whose workers joined the
    scheduler and have all been gone for :data:`JOB_GONE_GRACE` seconds is dropped from the cluster's
    spec (closing it, a harmless ``scancel`` of a finished job) and ``scale(jobs=jobs)`` submits a new
    one; the scheduler had already given its tasks to the other workers. Whether a job's worker joined
    is what the scheduler saw (``joined``, a scheduler plugin), not only who is there at a check: a job
    that joins and ends between two checks is replaced too. Jobs that never had a worker are left to
    :func:`wait_for_jobs`. ``replaced`` lists ``(worker name, job id)`` of each ended job."""

    EVERY = 2.0                     # seconds between checks (a test sets it longer)

    def __init__(self, cluster, jobs: int, *, every: float | None = None, grace: float = JOB_GONE_GRACE, say=print):
        from tornado.ioloop import PeriodicCallback
        self.cluster, self.jobs, self.grace, self.say = cluster, jobs, grace, say
        self.seen: set = set()
        self.gone: dict = {}
        self.replaced: list = []
        self.used: set = set()          # every job (worker spec) name this cluster has had
        self.job_ids: dict = {}         # job (worker spec) name -> its batch job id, noted when a worker joins
        self.joined = _join_log_class()(on_join=self._note_job)
        every = self.EVERY if every is None else every
        self._pc = PeriodicCallback(self.check, every * 1000)
        cluster.loop.add_callback(self._start)

    def _note_job(self, worker: str) -> None:
        """Note the batch job id of the job that ``worker`` belongs to (its Job object may be gone by the
        time the job's end is noticed: SpecCluster drops a lost worker's after a timeout)."""
        for name, spec in self.cluster.worker_spec.items():
            names = {f"{name}{s}" for s in spec["group"]} if "group" in spec else {str(name)}
            job_id = getattr(self.cluster.workers.get(name), "job_id", None)
            if worker in names and job_id:
                self.job_ids[name] = job_id

    def _start(self) -> None:
        scheduler = getattr(self.cluster, "scheduler", None)
        if hasattr(scheduler, "add_plugin"):    # the scheduler runs in this process (dask-jobqueue's default)
            scheduler.add_plugin(self.joined)
            self.joined.names |= {str(ws.name) for ws in scheduler.workers.values()}
        self._pc.start()

    def check(self) -> None:
        import time

        from distributed.core import Status
        c = self.cluster
        if c.status in (Status.closing, Status.closed, Status.failed):
            self._pc.stop()
            return
        present = {str(w.get("name")) for w in (c.scheduler_info or {}).get("workers", {}).values()}
        now = time.monotonic()
        ended = []
        for name, spec in list(c.worker_spec.items()):
            names = {f"{name}{s}" for s in spec["group"]} if "group" in spec else {str(name)}
            if names & present:
                self.seen.add(name)
                self.gone.pop(name, None)
                continue
            if names & self.joined.names:       # joined, and gone before this check saw it
                self.seen.add(name)
            if name in self.seen and now - self.gone.setdefault(name, now) >= self.grace:
                ended.append(name)
        self.used.update(c.worker_spec)
        if not ended:
            return
        for name in ended:
            job_id = getattr(c.workers.get(name), "job_id", None) or self.job_ids.get(name)
            del c.worker_spec[name]
            self.seen.discard(name)
            self.gone.pop(name, None)
            self.replaced.append((name, job_id))
            self.say(f"cluster: job {job_id} ({name}) ended (cancelled, walltime reached or node lost); its "
                     "unfinished tasks go to other workers, and a new job is submitted", flush=True)
        # New jobs get names never used: SpecCluster would take a name still held by the ended job as
        # running (nothing submitted), and its lost-worker timer for the old worker would close a new
        # job of that name that has not started yet.
        while c._new_worker_name(c._i) in self.used or c._new_worker_name(c._i) in c.workers:
            c._i += 1
        c.scale(jobs=self.jobs)


def slurm_queue(job_ids) -> dict | None:
    """``{job id: (state, reason)}`` of those of ``job_ids`` still in SLURM's queue (``squeue``, this
    user's jobs); None when squeue does not answer."""
    import getpass
    import subprocess
    ids = {str(j) for j in job_ids if j}
    try:
        r = subprocess.run(["squeue", "-h", "-u", getpass.getuser(), "-o", "%i|%T|%r"], capture_output=True,
                           text=True, timeout=30)
    except (OSError, subprocess.TimeoutExpired):
        return None
    if r.returncode != 0:
        return None
    out = {}
    for line in r.stdout.splitlines():
        jid, _, rest = line.strip().partition("|")
        state, _, reason = rest.partition("|")
        if jid in ids:
            out[jid] = (state, reason)
    return out


def wait_for_jobs(conn: Connection, jobs: int, *, say=print) -> None:
    """Return once a worker of the batch jobs has joined the scheduler (one that joined and has gone
    since counts: the keeper submits its job again), noting every :data:`JOB_WAIT_NOTE`
    seconds what the queue says of the jobs. Jobs may wait in a queue for hours, so there is no time
    limit, but ClusterError (exit 2) when the jobs cannot bring workers: not submitted within
    :data:`JOB_SUBMIT_TIMEOUT` s, pending for a reason that never clears (:data:`HOPELESS`), or all ended
    without a worker joining (the job script failed: its output is in ``log_directory``, else
    ``slurm-<id>.out`` in the submitting directory)."""
    import time
    cluster = conn.cluster
    keeper = getattr(cluster, "denoise_keeper", None)

    def joined() -> bool:               # one there now, or one that joined and has gone (the keeper replaces it)
        return bool(conn.n_workers() or (keeper is not None and keeper.joined.names))
    t0 = last = time.monotonic()
    while not joined():
        now = time.monotonic()
        ids = [getattr(j, "job_id", None) for j in list(cluster.workers.values())]
        submitted = [j for j in ids if j]
        if not submitted and now - t0 > JOB_SUBMIT_TIMEOUT:
            raise ClusterError(f"no {conn.kind} worker job was submitted within {JOB_SUBMIT_TIMEOUT:g} s (the "
                               "submit command failed; its error is logged above); check the job script "
                               "(pipeline.cluster.jobqueue_cluster(cfg).job_script(), docs/cluster.md)")
        queue = slurm_queue(submitted) if conn.kind == "slurm" and submitted else None
        if queue is not None:
            stuck = sorted(f"{j} {s} ({r})" for j, (s, r) in queue.items() if s == "PENDING" and r in HOPELESS)
            if stuck and len(stuck) == len(queue):
                raise ClusterError(f"the worker jobs can never start: squeue says {', '.join(stuck)}; ask "
                                   f"dataset.cluster.jobqueue for what the partition allows ({job_request(cluster)})")
            if not queue and len(submitted) >= min(jobs, len(ids)) and not joined():
                logs = (getattr(getattr(cluster, "_dummy_job", None), "log_directory", None)
                        or "slurm-<job id>.out in the submitting directory")
                raise ClusterError(f"the worker job(s) {', '.join(submitted)} ended before a worker joined; the "
                                   f"job script failed (its output: {logs}); check python, the prologue and "
                                   "that the scheduler's address is reachable from the nodes")
        if now - last >= JOB_WAIT_NOTE or (last == t0 and now - t0 >= 5.0):
            last = now
            what = (", ".join(f"{j} {s}" + (f" ({r})" if r and r != "None" else "")
                              for j, (s, r) in sorted(queue.items())) if queue
                    else f"{len(submitted)} of {len(ids)} submitted")
            say(f"cluster: waiting for the first worker of the {conn.kind} jobs ({now - t0:.0f} s so far; "
                f"{what}); Ctrl-C stops", flush=True)
        time.sleep(1.0)


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
