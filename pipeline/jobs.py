"""Batch clusters (``cluster.kind: slurm`` / ``pbs``) through dask-jobqueue: the cluster and what every
worker needs written into its job script (:func:`job_settings`); a job SLURM could never run refused
before anything is submitted (``sbatch --test-only``, :func:`check_job_submission`); the wait, saying what
the queue says, for the first worker (:func:`wait_for_jobs`); and a job that ends mid-run (``scancel``,
its walltime, a lost node) submitted again (:class:`JobKeeper`). :func:`pipeline.cluster.connect` uses them.
"""
from __future__ import annotations

import os
import sys

from core.checks import is_int, is_number, need
from pipeline.config import ClusterConfig
from pipeline.errors import ClusterError, ConfigError
from pipeline.cluster_settings import NO_DASHBOARD, PRELOAD, dashboard_bind, make_security


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
        self.renewed = 0                # jobs submitted again so far (their names: CLUSTER-rN)
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
        # job of that name that has not started yet. So the keeper adds their specs itself (the cluster's
        # public ``worker_spec`` and ``new_spec``, as ``SpecCluster.scale`` does with names of its own),
        # and ``scale`` then starts them.
        for _ in ended:
            name = self._unused_name()
            c.worker_spec[name] = c.new_spec
            self.used.add(name)
        c.scale(jobs=self.jobs)

    def _unused_name(self) -> str:
        """A job name this cluster has never had: ``CLUSTER-rN``."""
        c = self.cluster
        while True:
            self.renewed += 1
            name = f"{c.name}-r{self.renewed}"
            if name not in self.used and name not in c.workers and name not in c.worker_spec:
                return name


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


def wait_for_jobs(conn, jobs: int, *, say=print) -> None:
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
                               "(pipeline.jobs.jobqueue_cluster(cfg).job_script(), docs/cluster.md)")
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
