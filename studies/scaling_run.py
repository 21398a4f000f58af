"""Running a scaling study (:mod:`studies.scaling`): its stores, its runs side by side, their evaluation
on the held-out frames, and what rendering costs (``pipeline.estimate``).

Each job runs in a worker process (``parallel`` at a time, ``threads`` torch threads each) and writes its
folder under ``OUT/runs``: ``checkpoint.pt`` and ``metrics.csv`` (``training.loop.train``), ``run.log``
(what training printed) and ``scaling-run.json``: the job (its settings and clips), the held-out store's
identity and the evaluation (``training.evaluate``: per-frame metrics, means, ``ci95``). A job whose
``scaling-run.json`` matches it is finished and skipped; one interrupted mid-way resumes from its
checkpoint. The stores are ``pipeline dataset`` runs (``pipeline.dataset.run_dataset``), which
resume too.
"""
from __future__ import annotations

import contextlib
import hashlib
import json
import os
import time
import warnings
from pathlib import Path

from core import interrupts
from training.errors import DataError
from training.jsonio import write as write_json
from .scaling import REALISM_NONE, Job, ScalingConfig, clip_table, plan

RECORD = "scaling-run.json"


def ensure_store(dcfg, out: Path, workers: int | None, progress: bool, shared: bool = False) -> str:
    """Render (or resume, or find complete) the store of dataset config ``dcfg``: at its ``out`` if it
    names one, else ``OUT/stores/<name>.zarr`` (``shared``: where ``python -m pipeline dataset`` puts it,
    ``$DENOISE_DATA/<name>.zarr``, as the hard-case suite whose store ``make hard-cases`` reads).
    DataError when frames failed (a rerun retries them)."""
    from pipeline.dataset import run_dataset
    from pipeline.errors import PipelineError
    from stores.errors import StoreError
    path = dcfg.store_path(dcfg.out or (None if shared else f"{out / 'stores'}/"))
    try:
        summary = run_dataset(dcfg, out=path, workers=workers, progress=progress, say=print)
    except (PipelineError, StoreError) as e:
        raise DataError(f"dataset {dcfg.name!r} at {path}: {e}") from e
    if not summary["ok"]:
        raise DataError(f"dataset {dcfg.name!r} at {path} is not complete and valid ({summary['complete']}/"
                        f"{summary['frames']} frames, failed: {sorted(summary['failed'])}); run the command again "
                        "to retry the frames that failed")
    return path


def heldout_identity(store) -> dict:
    from training.loop import store_identity
    return store_identity(store)


def finished(job: Job, run_dir: Path, heldout: dict) -> dict | None:
    """The job's record when its folder holds one for exactly this job and held-out store, else None."""
    f = run_dir / RECORD
    if not f.is_file():
        return None
    try:
        rec = json.loads(f.read_text())
    except (OSError, ValueError):
        return None
    return rec if rec.get("job") == json.loads(json.dumps(job.to_dict())) and rec.get("heldout") == heldout else None


def _trained(run_dir: Path, steps: int) -> bool:
    """Whether the run folder's checkpoint reached ``steps`` (train would do nothing more)."""
    ck = run_dir / "checkpoint.pt"
    if not ck.is_file():
        return False
    from training import checkpoint
    return int(checkpoint.load(ck)["step"]) >= steps


def run_job(job: dict, train_store: str, heldout_store: str, run_dir: str, threads: int, flip: bool,
            heldout: dict, hard_store: str | None = None, real_stores: dict | None = None) -> dict:
    """Train (or resume) and evaluate one job in this process (a worker of :func:`run_jobs`); writes its
    record and returns ``{"name", "mean", "seconds"}``. Training's output goes to ``run_dir/run.log``.
    With ``hard_store`` (the held-out hard-case suite), a hard-share run and a baseline are evaluated on
    every frame of it as well (``hard_evaluation`` in the record); with ``real_stores`` (``{filter: store}``
    of the held-out real-scene suite), a realism run and a baseline on each (``real_evaluation``)."""
    import torch

    from training.accel import tune_allocator
    from training.loop import train
    tune_allocator()
    torch.set_num_threads(int(threads))
    job = Job(**{k: (tuple(v) if k == "clips" else v) for k, v in job.items()})
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    t0, c0 = time.perf_counter(), time.process_time()
    with open(run_dir / "run.log", "a") as log, contextlib.redirect_stdout(log), contextlib.redirect_stderr(log), \
            warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="training without validation")   # judged on the held-out store
        if job.kind != "baseline" and not _trained(run_dir, job.config().steps):
            train(job.config(), train_store, run_dir, progress=False)
        res = job_evaluation(job, run_dir, heldout_store, flip)
        hard = job_evaluation(job, run_dir, hard_store, flip, skip_bad_frames=True) \
            if hard_store and uses_suite(job) else None
        real = {f: job_evaluation(job, run_dir, st, flip, skip_bad_frames=True) for f, st in real_stores.items()} \
            if real_stores and uses_real(job) else None
    seconds = time.perf_counter() - t0
    write_json(run_dir / RECORD, {"job": job.to_dict(), "heldout": heldout, "seconds": seconds,
                                  "cpu_seconds": time.process_time() - c0, "evaluation": res,
                                  **({"hard_evaluation": hard} if hard is not None else {}),
                                  **({"real_evaluation": real} if real is not None else {})})
    return {"name": job.name, "mean": res["mean"], "seconds": seconds, "cpu_seconds": time.process_time() - c0}


def job_evaluation(job: Job, run_dir: Path, store: str, flip: bool, skip_bad_frames: bool = False) -> dict:
    """``training.evaluate.evaluate`` of a run's checkpoint (or a baseline) on the test split of ``store``
    (``skip_bad_frames``: the frames ``validate`` flags left out and named, as on the hard-case suite)."""
    from training.evaluate import evaluate
    if job.kind == "baseline":
        res = evaluate(job.method, store, split="test", spp=job.spp, with_flip=flip, skip_bad_frames=skip_bad_frames,
                       baseline_input=job.baseline_input, device="auto")
    else:
        cfg = job.config()
        res = evaluate(run_dir / "checkpoint.pt", store, split="test", with_flip=flip, skip_bad_frames=skip_bad_frames,
                       device=cfg.device, precision=cfg.precision)
    return {k: v for k, v in res.items() if k not in ("images", "sample_map")}


def uses_suite(job: Job) -> bool:
    """Whether a job is evaluated on a study's hard-case suite too: the share axis' runs and the baselines."""
    return job.kind in ("hard", "baseline")


def uses_real(job: Job) -> bool:
    """Whether a job is evaluated on a study's real-scene suite too: the realism axis' runs and the baselines."""
    return job.kind in ("realism", "baseline")


def job_heldout(job: Job, heldout: dict, suite: dict | None, real: dict | None = None,
                trained_on: dict | None = None) -> dict:
    """What a job's record must have been evaluated on to count as finished: the held-out store, and the
    suites for the jobs :func:`uses_suite` and :func:`uses_real` (so adding a suite to a study leaves its
    other runs finished); for a realism run, the identity of the level's store it trained on
    (``trained_on``: a level whose settings changed is a new store, and its runs are run again)."""
    out = {**heldout, "hard_cases": suite} if suite is not None and uses_suite(job) else heldout
    out = {**out, "real_scenes": real} if real is not None and uses_real(job) else out
    return {**out, "trained_on": trained_on} if trained_on is not None and job.kind == "realism" else out


def _ignore_interrupt() -> None:
    """Pool worker initializer: Ctrl-C is the parent's to handle (it terminates the workers), so a worker
    prints no traceback of its own; checkpoints and records are written atomically, so a killed run
    resumes from its last checkpoint. The parent's terminate (SIGTERM) ends a worker through ``sys.exit``,
    so that it cleans up as it exits: killed outright, it left the semaphores it had made (numcodecs'
    Blosc lock) to multiprocessing's resource tracker, which warned of them after the study's last line."""
    import signal
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, _exit_on_terminate)


def _exit_on_terminate(signum, frame) -> None:
    import sys
    sys.exit(128 + signum)


def _next(done, timeout: float = 1.0):
    """The next finished job from the pool's callbacks (waits in short steps, so Ctrl-C is seen at once)."""
    import queue
    while True:
        try:
            return done.get(timeout=timeout)
        except queue.Empty:
            continue


def run_jobs(jobs: list[Job], train_store: str, heldout_store: str, out: Path, parallel: int, threads: int,
             flip: bool, log=print, hard_store: str | None = None, level_stores: dict | None = None,
             real_stores: dict | None = None) -> dict[str, dict]:
    """Every job's record (``name -> record``): finished ones read back, the others run ``parallel`` at a
    time in fresh worker processes (training and evaluating; one line each as they end). Ctrl-C, or a run
    that fails, stops every worker: finished runs stay, interrupted ones resume from their checkpoints.
    ``level_stores``: the realism axis' training store of each level; ``real_stores``: its suite's store of
    each pixel filter."""
    import multiprocessing
    import queue

    from training.data import open_store
    heldout = json.loads(json.dumps(heldout_identity(open_store(heldout_store))))
    suite = json.loads(json.dumps(heldout_identity(open_store(hard_store)))) if hard_store else None
    real = json.loads(json.dumps({f: heldout_identity(open_store(p)) for f, p in real_stores.items()})) \
        if real_stores else None
    level_stores = level_stores or {}
    trained_on = json.loads(json.dumps({lv: heldout_identity(open_store(p)) for lv, p in level_stores.items()}))
    runs = out / "runs"
    records, todo = {}, []
    for job in jobs:
        rec = finished(job, runs / job.name, job_heldout(job, heldout, suite, real, trained_on.get(job.level)))
        if rec is None:
            todo.append(job)
        else:
            records[job.name] = rec
    log(f"scaling: {len(jobs)} runs and baselines, {len(records)} finished, {len(todo)} to run "
        f"({parallel} at a time, {threads} thread(s) each)")
    if not todo:
        return records
    t0, done, pool = time.perf_counter(), queue.Queue(), None
    try:
        with interrupts.held_back():     # the workers begin with Ctrl-C blocked (before _ignore_interrupt runs)
            pool = multiprocessing.get_context("spawn").Pool(parallel, initializer=_ignore_interrupt)
        for j in todo:
            args = (j.to_dict(), level_stores.get(j.level, train_store), heldout_store, str(runs / j.name), threads,
                    flip, job_heldout(j, heldout, suite, real, trained_on.get(j.level)), hard_store, real_stores)
            pool.apply_async(run_job, args, callback=lambda r: done.put((r, None)),
                             error_callback=lambda e, name=j.name: done.put((name, e)))
        for k in range(1, len(todo) + 1):
            res, err = _next(done)
            if err is not None:
                log(f"scaling: run {res} failed: {type(err).__name__}: {err}")
                raise err
            records[res["name"]] = json.loads((runs / res["name"] / RECORD).read_text())
            m = res["mean"]
            log(f"  [{k}/{len(todo)}] {res['name']}: relMSE {m['relmse']:.4g}, PSNR {m['psnr']:.2f} dB "
                f"({res['seconds']:.0f} s, {res['cpu_seconds']:.0f} CPU-s; {time.perf_counter() - t0:.0f} s so far)")
    except BaseException:
        if pool is not None:
            pool.terminate()
            pool.join()
        raise
    pool.close()
    pool.join()
    return records


def rendering_costs(dcfg, out: Path, workers: int | None, store=None, log=print) -> dict:
    """What a frame of the training config costs to render and store, by ``pipeline.estimate``'s
    calibration on this machine (cached in ``OUT/estimate.json`` for this config), with the store's own
    measured render seconds a frame beside it (``frames/render_seconds``) when ``store`` is given."""
    from pipeline.estimate import calibrate, local_slots, predict
    key = hashlib.sha256(json.dumps(dcfg.content_dict(), sort_keys=True, default=str).encode()).hexdigest()
    path = out / "estimate.json"
    if path.is_file():
        cached = json.loads(path.read_text())
        if cached.get("config_sha256") == key:
            return cached
    threads = dcfg.cluster.threads_per_worker
    workers = workers or local_slots(threads)
    log(f"scaling: calibrating the rendering cost of {dcfg.name!r} (pipeline estimate)")
    cal = calibrate(dcfg, per_group=1, threads=threads, concurrent=min(workers, local_slots(threads)), log=log)
    p = predict(dcfg, cal, workers)
    costs = {"config_sha256": key, "dataset": dcfg.name, "core_hours_per_frame": p["core_hours"] / p["frames"],
             "bytes_per_frame": cal["bytes_per_frame"], "store_fixed_bytes": cal["store_fixed_bytes"],
             "workers": workers, "threads": threads, "calibration_frames": len(cal["frames"])}
    if store is not None:
        import numpy as np
        secs = np.asarray(store.meta_column("render_seconds"), np.float64) * threads   # a task's wall x its threads
        costs["measured_core_hours_per_frame"] = float(secs[secs > 0].mean() / 3600.0) if (secs > 0).any() else None
    write_json(path, costs)
    return costs


def flat_stores(stores: dict) -> dict:
    """``{name: path}`` of every store a study read (a mapping of several, such as the realism levels', as
    ``<key>-<name>``)."""
    out = {}
    for k, v in stores.items():
        out.update({f"{k}-{n}": p for n, p in v.items()} if isinstance(v, dict) else {k: v})
    return out


def realism_stores(scfg: ScalingConfig, out: Path, train_path: str, workers: int | None,
                   progress: bool) -> tuple[dict, dict]:
    """The realism axis' stores, rendered or resumed: ``{level: training store}`` (``none``: the study's own
    training store) and ``{filter: real-scene suite store}`` (where ``make real-scenes`` puts them); two empty
    mappings without the axis."""
    if not scfg.realism_plan():
        return {}, {}
    levels = {REALISM_NONE: train_path}
    for name, dcfg in scfg.level_configs().items():
        if name != REALISM_NONE:
            levels[name] = ensure_store(dcfg, out, workers, progress)
    return levels, {f: ensure_store(c, out, workers, progress, shared=True) for f, c in scfg.suite_configs().items()}


def run_study(scfg: ScalingConfig, out=None, *, targets: dict | None = None, workers: int | None = None,
              progress: bool = True, log=print) -> dict:
    """The whole study (``studies.scaling``): the stores, every run, the analysis and the three files in
    ``out`` (default: the config's ``out``, else ``data/<name>``). ``targets`` (``{metric: value}``) are
    added to the config's. Returns the result written to ``scaling.json``. One study a folder at a time:
    ``out`` holds a :class:`stores.lock.StoreLock` while the study runs (a second is refused, naming the
    first; a dead one's is taken over)."""
    from stores.lock import StoreLock
    out = Path(out or scfg.out or f"data/{scfg.name}")
    with StoreLock(str(out), command=f"studies scaling {scfg.name}"):     # one study a folder at a time
        return _run_study(scfg, out, targets, workers, progress, log)


def _run_study(scfg: ScalingConfig, out: Path, targets: dict | None, workers: int | None, progress: bool,
               log) -> dict:
    from training.data import open_store
    from training.report import provenance
    from training.realscenes import frame_scenes
    from .scaling_report import analyse, price, write_report
    t0 = time.perf_counter()
    workers = workers or scfg.workers
    train_cfg, held_cfg = scfg.dataset_configs()
    train_path = ensure_store(train_cfg, out, workers, progress)
    held_path = ensure_store(held_cfg, out, workers, progress)
    hard_cfg = scfg.hard_config()
    hard_path = ensure_store(hard_cfg, out, workers, progress, shared=True) if hard_cfg is not None else None
    train_store = open_store(train_path)
    level_stores, real_stores = realism_stores(scfg, out, train_path, workers, progress)
    jobs, record = plan(scfg, clip_table(train_store, "train"),
                        {lv: clip_table(open_store(p), "train") for lv, p in level_stores.items()})
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    parallel = scfg.parallel or max(1, cores // scfg.threads)
    records = run_jobs(jobs, train_path, held_path, out, parallel, scfg.threads, scfg.flip, log, hard_path,
                       level_stores, real_stores)
    targets = {k: float(v) for k, v in {**scfg.targets, **(targets or {})}.items() if v is not None}
    suite_cases = ({i: str(c) for i, c in enumerate(open_store(hard_path).meta_column("case"))}
                   if hard_path else None)
    result = analyse(scfg, jobs, records, targets, suite_cases=suite_cases,
                     real_scenes={f: frame_scenes(open_store(p)) for f, p in real_stores.items()})
    if any("frames" in a for a in result["targets"]):           # an answer to price: calibrate (or read the cache)
        result["costs"] = rendering_costs(train_cfg, out, workers, train_store, log)
        price(result["targets"], result["costs"])
    stores = {"train": train_path, "heldout": held_path, **({"hard_cases": hard_path} if hard_path else {}),
              **({"levels": level_stores, "real_scenes": real_stores} if real_stores else {})}
    result.update(config=scfg.to_dict(), stores=stores, plan=record,
                  seconds=time.perf_counter() - t0,
                  provenance=provenance([], flat_stores(stores), {"out": str(out)}))
    write_report(out, result, scfg)
    files = "scaling.md, scaling.png" if result["models"] else "scaling.md"
    log(f"scaling: wrote {out}/{files} and scaling.json in {result['seconds']:.0f} s")
    from .scaling_report import targets_markdown
    for line in [mod["verdict"] for mod in result["models"].values()] + targets_markdown(result["targets"],
                                                                                           result["costs"]):
        log("  " + line.lstrip("- ").replace("**", ""))
    return result
