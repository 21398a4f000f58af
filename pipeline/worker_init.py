"""What every Dask worker process needs before its first task. ``pipeline.cluster.connect`` installs it
on every worker through the ``pipeline.cluster.WorkerInit`` plugin (importing this module from the
plugin's setup, in the worker's main thread), so workers need no flag; ``dask worker --preload
pipeline.worker_init`` does the same and still works (LocalClusters use both).

Importing it, in the worker process's main thread:
- imports pymeshlab there, where it is installed: pymeshlab (Qt plugins) imported first from a
  non-main thread corrupts the heap (glibc's ``malloc_consolidate(): unaligned fastbin chunk
  detected``), and Dask runs tasks in executor threads (without it, ``scene_gen.pymeshlab: false``
  scenes need none);
- points drjit at a libLLVM >= 16 and keeps BLAS/OpenMP pools at one thread per worker thread;
- in the worker processes of a ``LocalCluster`` that ``pipeline.cluster`` starts (``$DENOISE_LOCAL_WORKER``
  set through the nanny's environment), blocks SIGINT (:func:`ignore_interrupts`): a terminal's
  Ctrl-C reaches the whole process group, and a worker that took it would close "gracefully", so its
  nanny would not replace it and the run would wait for it forever; the client alone handles Ctrl-C
  (it stops the run with exit code 130 and closes the workers). Workers started by ``dask worker``
  or batch jobs keep their own signal handling. Those workers also leave out distributed's
  "Compute Failed" tracebacks (:func:`quiet_task_failures`): the client prints each failed frame.
"""
from __future__ import annotations

import importlib
import os
import signal

from pipeline.errors import PipelineError

LOCAL_WORKER_ENV = "DENOISE_LOCAL_WORKER"
# glibc's allocator for the worker processes, read when a process starts (so set in the environment they are
# spawned with). Dask's nanny sets MALLOC_TRIM_THRESHOLD_=65536 for its workers, and setting any of these
# turns off glibc's dynamic mmap threshold: it stays at 128 KiB, so every temporary numpy array above that
# is mmapped, faulted in and unmapped afresh. The bench's four scene loads took 3.3-3.6 s with it against
# 2.6-2.7 s with glibc's defaults (docs/throughput.md). These are the defaults' own ceilings on 64-bit
# (the mmap threshold grows to 32 MiB, the trim threshold to twice that); a value set here already wins.
MALLOC_ENV = {"MALLOC_MMAP_THRESHOLD_": "33554432", "MALLOC_TRIM_THRESHOLD_": "67108864"}
GPU_SPLIT_ENV = "DENOISE_GPU_PER_WORKER"    # job scripts of jobqueue.gpus_per_job: the job's workers (= GPUs)


class GPUShortageError(PipelineError, RuntimeError):
    """A GPU job's worker would share a GPU with another worker of its job: the job sees fewer GPUs than it
    has workers. The worker does not start; the message names the job's GPUs and workers."""


def gpu_for_worker(name: str, visible: str | None, workers: int | None = None) -> str | None:
    """The ``CUDA_VISIBLE_DEVICES`` of worker ``name`` of a job whose GPUs are ``visible``: a job of N
    workers names them ``<job>-0`` .. ``<job>-(N-1)`` (``dask worker --nworkers N``), and worker i keeps
    the job's GPU i; None where there is nothing to split (one worker; or, without ``workers``, one GPU or
    none). ``workers``: the job's workers (``$DENOISE_GPU_PER_WORKER``), so that no two share a GPU: a job
    that sees fewer GPUs raises :class:`GPUShortageError`, and one whose batch system sets no
    ``CUDA_VISIBLE_DEVICES`` keeps GPU i of the node."""
    devices = [d.strip() for d in (visible or "").split(",") if d.strip()]
    if workers is not None and workers > 1:
        devices = devices or [str(i) for i in range(workers)]
        if len(devices) < workers:
            raise GPUShortageError(f"worker {name}: its job has {workers} workers but sees {len(devices)} GPU(s) "
                                   f"(CUDA_VISIBLE_DEVICES={visible}); two would share one. Ask the batch system "
                                   f"for {workers} GPUs a job (jobqueue.gpus_per_job, and its directives)")
    elif len(devices) < 2:
        return None
    tail = str(name).rsplit("-", 1)[-1]
    if not tail.isdigit():
        if workers is not None and workers > 1:
            raise GPUShortageError(f"worker {name}: not named <job>-<i> as `dask worker --nworkers "
                                   f"{workers}` names them, so which of the job's GPUs is its own is unknown")
        return None
    if workers is not None and workers > 1 and int(tail) >= workers:
        raise GPUShortageError(f"worker {name} is not one of its job's {workers} workers (<job>-0 .. "
                               f"<job>-{workers - 1})")
    return devices[int(tail) % len(devices)]


def prepare_environment() -> None:
    """drjit's libLLVM, single-threaded BLAS/OpenMP pools, glibc's allocator thresholds (:data:`MALLOC_ENV`;
    a nanny passes this process's value of MALLOC_TRIM_THRESHOLD_ on in place of its own) and botocore's
    retries (inherited by worker processes)."""
    from core.errors import VariantError
    from core.variant import find_libllvm
    try:
        lib = find_libllvm()
    except VariantError:
        lib = None
    if lib:
        os.environ.setdefault("DRJIT_LIBLLVM_PATH", lib)
    for k in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ.setdefault(k, "1")
    for k, v in MALLOC_ENV.items():
        os.environ.setdefault(k, v)
    from stores.objectstore import quiet_abandoned_requests, retry_defaults
    retry_defaults()                # botocore's bounded retries for stores at s3:// URLs
    quiet_abandoned_requests()      # and no traceback of each request dropped when they are spent


def ignore_interrupts() -> None:
    """Block SIGINT in this process's main thread (threads started later inherit the mask) and ignore it
    process-wide: it is never delivered, so neither Python nor Mitsuba's render loop (which installs its
    own SIGINT handler during ``mi.render`` and would cut the render short) sees it."""
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def spawn_ignoring_interrupts() -> None:
    """Start this process's multiprocessing children (a LocalCluster's worker processes, and the resource
    tracker) with SIGINT ignored from their first instruction, through a two-line ``sh`` wrapper around
    this Python (``trap '' INT``: an ignored signal stays ignored across ``exec``, and Python then leaves
    it so). :func:`ignore_interrupts` runs only once a worker has imported Dask; a terminal's Ctrl-C that
    reached a worker still importing printed its ``KeyboardInterrupt`` traceback (the chaos run,
    ``scripts/chaos.py``, met it). multiprocessing takes one executable path, no arguments, so the
    wrapper is a file, written once a process into a temporary folder.

    And the resource tracker's warning of the semaphores it cleans up after a main process that was
    killed (``resource_tracker: There appear to be N leaked semaphore objects``) is off: they are Dask's,
    the tracker frees them, and the run resumes; the warning only told the user what was already done."""
    import atexit
    import multiprocessing
    import shlex
    import shutil
    import sys
    import tempfile
    global _WRAPPER
    if _WRAPPER is None:
        folder = tempfile.mkdtemp(prefix="denoise-spawn-")
        atexit.register(shutil.rmtree, folder, True)
        path = os.path.join(folder, "python")
        with open(path, "w") as f:
            f.write(f"#!/bin/sh\ntrap '' INT\nexec {shlex.quote(sys.executable)} \"$@\"\n")
        os.chmod(path, 0o755)
        _WRAPPER = path
    multiprocessing.get_context("spawn").set_executable(_WRAPPER)
    quiet = "ignore:resource_tracker:UserWarning"      # -W of every Python that multiprocessing spawns
    if quiet not in sys.warnoptions:
        sys.warnoptions.append(quiet)


_WRAPPER: str | None = None


def quiet_task_failures() -> None:
    """Drop distributed's "Compute Failed" log record (the task's whole traceback, once per attempt), and
    the failed heartbeat of a run's last moments, in this worker: the client that started it records
    each failed frame's error in the store (``status/error``) and prints it in one line in its summary."""
    import logging

    class _NoComputeFailed(logging.Filter):
        def filter(self, record):
            # and the heartbeat that meets the scheduler already closed as the run ends (a traceback
            # after the run's summary, now and then): the scheduler lives in the client's process, so
            # a LocalCluster worker outliving it has nothing to tell anyone
            return not str(record.msg).startswith(("Compute Failed",
                                                   "Failed to communicate with scheduler during heartbeat"))
    logging.getLogger("distributed.worker").addFilter(_NoComputeFailed())


prepare_environment()
if os.environ.get(LOCAL_WORKER_ENV) == "1":
    ignore_interrupts()
    quiet_task_failures()
try:
    importlib.import_module("pymeshlab")     # first imported in this, the main, thread (scene_gen.meshes._pymeshlab)
except ImportError:   # a machine without it (scene_gen.pymeshlab: false); a mesh that needs it says so
    pass


def dask_setup(worker) -> None:  # noqa: D401 - Dask's preload hook
    """In the workers of a GPU job (``$DENOISE_GPU_PER_WORKER``): keep this worker's GPU only, before
    anything initialises CUDA (:func:`gpu_for_worker`). Otherwise importing this module did the work."""
    split = os.environ.get(GPU_SPLIT_ENV, "")
    if split.isdigit() and int(split) >= 1:
        gpu = gpu_for_worker(worker.name, os.environ.get("CUDA_VISIBLE_DEVICES"), int(split))
        if gpu is not None:
            os.environ["CUDA_VISIBLE_DEVICES"] = gpu
