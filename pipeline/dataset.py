"""Build (or resume) a dataset from its config on a Dask cluster: :func:`run_dataset`, a library call that
raises and never prints (``python -m pipeline dataset``, :mod:`pipeline.cli_dataset`, prints its lines;
the scaling study and the benchmarks call it directly).

Order of work (everything that can be wrong is checked before a pixel is rendered):

1. check an existing store at the target matches the config (else :class:`StoreMismatchError`);
2. start a LocalCluster sized to the machine, or reach the scheduler / the configured cluster
   (unreachable: ``ClusterError``);
3. create the store, or open it and list the frames whose ``status/complete`` is not set (resume);
4. submit the graph (``pipeline.graph``) for those frames only; a frame whose task still fails after
   ``tasks.retries`` retries is recorded in the store (``status/error``) and the rest goes on;
5. validate the frames written and return the summary (store, frames, failures, timings, validation).

A KeyboardInterrupt anywhere becomes :class:`DatasetInterrupted`, whose text says what stays; frames
already written stay complete and the same call finishes the others.
"""
from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from pipeline.config import DatasetConfig
from pipeline.errors import ConfigError, PipelineError
from core.errors import is_disk_full
from stores.errors import store_full, unreachable_cause

class StoreMismatchError(ConfigError):
    """The store at the target path was made from a different dataset config."""


class DatasetInterrupted(KeyboardInterrupt):
    """Ctrl-C stopped a run: its message, the one line ``python -m pipeline`` prints after ``interrupted:``,
    says where the complete frames stay and that the same command resumes."""

    def __init__(self, store: str):
        super().__init__(f"complete frames stay in {store}; run the same command again to resume")


def _quiet_interrupted_sync() -> None:
    """Leave out the one error distributed logs when Ctrl-C lands at the start of a blocking client call:
    its ``sync()`` asks the event loop to cancel a future it has not made yet, which fails there
    (NameError: cannot access free variable 'future'), and tornado printed that with its traceback before
    the command's line. Nothing is lost: the call was interrupted and the run stops. Anything else the
    loop logs is printed as before."""
    import logging
    log = logging.getLogger("tornado.application")
    if not any(f is _drop_interrupted_sync for f in log.filters):
        log.addFilter(_drop_interrupted_sync)


def _drop_interrupted_sync(record) -> bool:
    kind, err, tb = record.exc_info or (None, None, None)
    while tb is not None and tb.tb_next is not None:
        tb = tb.tb_next
    return not (kind is NameError and "'future'" in str(err) and tb is not None
                and tb.tb_frame.f_code.co_name == "cancel"
                and tb.tb_frame.f_code.co_filename.endswith(os.path.join("distributed", "utils.py")))


def check_existing_store(cfg: DatasetConfig, store: str, *, overwrite: bool = False) -> DatasetConfig:
    """Check what is at ``store`` before anything starts (metadata only: no frame data or completion
    flag is read, so a damaged chunk is left to the resume, which re-renders its frame); returns the
    config to run: ``cfg``, or for a store made before ``clip_ids`` existed, ``cfg`` with
    ``clip_ids: scene_seed`` (its frames keep their split).
    Raises ForeignStoreError for a non-empty folder (or a file) that is not a store,
    StoreMismatchError for a store made from another config (both unless ``overwrite``; a file is
    refused even then)."""
    from stores import create, schema
    from stores.errors import ForeignStoreError, IncompleteStoreError, StoreCorruptionError
    if "://" not in store and os.path.lexists(store) and not os.path.isdir(store):
        raise ForeignStoreError(f"--out {store} is a file, not a folder; choose another --out")
    if overwrite:
        create.refuse_link(store)                   # never delete through a symbolic link
    found = create.foreign_entries(store)
    if found:
        if overwrite:
            return cfg
        shown = ", ".join(found[:5]) + (f", ... ({len(found)} entries)" if len(found) > 5 else "")
        raise ForeignStoreError(f"{store} is a non-empty folder that is not a store made by this pipeline "
                                f"(it holds {shown}); nothing was touched: choose another --out, or pass "
                                "--overwrite to delete its contents and build the dataset there")
    if not schema.store_exists(store):
        return cfg
    try:
        root, layout = schema.open_group(store, mode="r")
    except IncompleteStoreError:
        return cfg                              # made again by open_or_create
    except (ForeignStoreError, StoreCorruptionError):     # not ours, or damaged metadata: --overwrite replaces it
        if overwrite:
            return cfg
        raise
    if overwrite:
        return cfg
    have = dict(root.attrs).get("config") or {}
    want = json.loads(json.dumps(cfg.content_dict()))
    if have != want and "clip_ids" not in have and cfg.clip_ids != "scene_seed":
        legacy = cfg.with_overrides(clip_ids="scene_seed")      # a store made before clip_ids existed
        if have == json.loads(json.dumps(legacy.content_dict())):
            cfg, want = legacy, have
    if have != want and (have.get("render") or {}).get("reference", "batch_means") == "batch_means":
        cfg, want = _legacy_reference(cfg, have, want)
    if have != want:
        _refuse_changed_files(store, have, want)
        keys = sorted(k for k in set(have) | set(want) if have.get(k) != want.get(k))
        raise StoreMismatchError(
            f"the store at {store} was made from a different dataset config (differs in: {', '.join(keys)}); "
            "use another --out, or --overwrite to delete it and start again")
    want_layout = cfg.store_layout()
    if not layout.frame_shape_compatible(want_layout) or layout.num_frames != want_layout.num_frames:
        raise StoreMismatchError(f"the store at {store} has layout {layout.to_dict()}, the config needs "
                                 f"{want_layout.to_dict()}")
    return cfg


def _refuse_changed_files(store: str, have: dict, want: dict) -> None:
    """Raise the one line that says which scene file changed, where a store's config and the run's differ
    only in the content hashes of a file group (``pipeline.groups.SceneGroup.to_dict``)."""
    a, b = have.get("scenes") or [], want.get("scenes") or []
    strip = lambda d: {**d, "scenes": [{k: v for k, v in g.items() if k != "sha256"} for g in d.get("scenes") or []]}  # noqa: E731
    if len(a) != len(b) or strip(have) != strip(want):
        return
    for i, (ga, gb) in enumerate(zip(a, b)):
        if ga.get("sha256") != gb.get("sha256"):
            raise StoreMismatchError(
                f"the store at {store} was made from other content of dataset.scenes[{i}].file {gb.get('file')!r}: "
                "a scene file (or a file it names) changed since; render it into another --out, or --overwrite "
                "to start again")


def check_scene_files(cfg: DatasetConfig) -> int:
    """Load every scene file of ``cfg``'s file groups once (``scene_gen.scene_files.inspect``) before a
    cluster starts, so a file that does not load, lacks a sensor and a camera, or needs a plugin the
    variant lacks is one line (``SceneFileError``, exit 2) rather than failed frames. Returns the count."""
    from scene_gen import scene_files
    seen = set()
    for g in cfg.scenes:
        for j in range(min(g.count, len(g.files))):
            src = g.file_source(j)
            key = (src["path"], repr(src["camera"]))
            if key not in seen:
                seen.add(key)
                scene_files.inspect(src["path"], scene_files.CameraSettings.from_dict(src["camera"]))
    return len(seen)


# render settings that did not exist before ``render.reference``: a store made then records none of them
_REFERENCE_KEYS = ("reference", "ref_max_times", "ref_times")


def _legacy_reference(cfg, have: dict, want: dict):
    """A store made before ``render.reference`` existed resumes with the method it was made with
    (``batch_means``) when the config is otherwise the store's; else ``(cfg, want)`` unchanged."""
    legacy = cfg.with_overrides(render={**cfg.render, "reference": "batch_means"})
    old, rec = json.loads(json.dumps(legacy.content_dict())), json.loads(json.dumps(have))
    for d in (old, rec):
        for k in _REFERENCE_KEYS:
            (d.get("render") or {}).pop(k, None)
    return (legacy, have) if old == rec else (cfg, want)


def _validate_run(store: str, written: list[int], checked: dict[int, list[str]] | None = None) -> dict:
    """The run's validation, without reading back what it rendered: the store's array metadata and the
    metadata damage of every frame (``stores.validate.validate_store`` with ``read_values=False``), the
    completeness and files of the frames ``written`` (or attempted) now, and their values as the write tasks checked
    them (``checked``: frame -> ``stores.fitness.check_values`` problems) plus the renderer's replaced
    NaN (``stores.fitness.renderer_findings``). Frames of earlier runs were checked by theirs;
    ``python -m pipeline validate`` reads every frame again. ``{'ok', 'problems', 'frames_checked'}``."""
    from stores.validate import validate_store
    rep = validate_store(store, sorted(written), read_values=False)
    problems = list(rep.problems) + [f"frame {f.index}: {p}" for f in rep.frames for p in f.problems]
    for i, found in sorted((checked or {}).items()):
        problems += [f"frame {i}: {p}" for p in found]
    return {"ok": not problems, "problems": problems, "frames_checked": len(written)}


def run_dataset(cfg: DatasetConfig, *, out: str | None = None, scheduler: str | None = None,
                workers: int | None = None, progress: bool = False, functions=None,
                overwrite: bool = False, say=None) -> dict:
    """Build (or resume) the dataset of ``cfg``; returns the summary dict. Prints nothing: what happens
    as it goes (the lock taken over, the resume, the cluster and its dashboard) is said through
    ``say(line)`` when given (the command line's ``print``), and ``progress`` shows a progress bar.

    The run holds the store's writer lock (``stores.lock.StoreLock``) from the first check to the
    summary: a second run on the same store is refused (StoreLockedError naming host, pid and start).
    ``overwrite`` deletes what is at the store path first. ``functions`` replaces the graph's task
    functions (tests inject failures with it).
    """
    store = cfg.store_path(out)
    try:
        return _run_dataset(cfg, store, scheduler=scheduler, workers=workers, progress=progress,
                            functions=functions, overwrite=overwrite, say=say or _silent)
    except KeyboardInterrupt:                   # anywhere in the run: the one line says what stays
        raise DatasetInterrupted(store) from None
    except Exception as e:
        from stores.errors import store_unreachable, unreachable_cause
        if "://" in store and unreachable_cause(e) is not None:
            raise store_unreachable(store, e) from None       # one line, exit 5: the store resumes
        raise


def _silent(line: str) -> None:
    """``say`` of a run whose caller wants no lines."""


def _run_dataset(cfg: DatasetConfig, store: str, *, scheduler, workers, progress, functions, overwrite,
                 say) -> dict:
    from stores.lock import StoreLock
    cfg = check_existing_store(cfg, store, overwrite=overwrite)   # before the lock and the cluster: costs nothing
    if any(g.files for g in cfg.scenes):
        say(f"scene files: {check_scene_files(cfg)} loaded and checked")
    check_cluster_settings(cfg, scheduler=scheduler, workers=workers)
    check_memory_before_start(cfg, scheduler=scheduler, workers=workers)
    if "://" not in store and not Path(store).parent.is_dir():
        try:
            Path(store).parent.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            from stores.errors import StorePathError
            raise StorePathError(f"--out {store}: cannot make its folder {Path(store).parent}: "
                                 f"{e.strerror or e}; choose another --out") from e
    with StoreLock(store, command=" ".join(sys.argv) or None) as lock:
        if lock.took_over:
            from stores.lock import describe
            say(f"lock: took over the lock of a dead run ({describe(lock.took_over)})")
        elif not lock.supported:
            say(f"lock: none for {store.split('://', 1)[0]}:// stores (s3:// and local paths are locked); run "
                   "one dataset command per store at a time")
        return _run_locked(cfg, store, scheduler=scheduler, workers=workers, progress=progress,
                           functions=functions, overwrite=overwrite, lock=lock, say=say)


def _run_locked(cfg: DatasetConfig, store: str, *, scheduler, workers, progress, functions, overwrite,
                lock=None, say=_silent) -> dict:
    from distributed import as_completed

    from pipeline import cluster as cl
    from pipeline.graph import build_graph
    from stores.writer import generation

    t0 = time.perf_counter()
    cfg = check_existing_store(cfg, store, overwrite=overwrite)  # again, now that this run holds the lock
    from stores.create import remove_partial_files
    left = remove_partial_files(store)        # a killed run's temporary files (held lock: no write is under way)
    if left:
        say(f"resume: removed {len(left)} temporary file(s) of a write cut short ({', '.join(left[:3])}"
               f"{', ...' if len(left) > 3 else ''})")
    say(f"dataset {cfg.name!r}: {cfg.num_scenes} scenes, {cfg.num_frames} frames at "
           f"{cfg.resolution[0]}x{cfg.resolution[1]} -> {store}")
    if not overwrite and frames_to_render(cfg, store) == []:     # a complete store: no cluster to start
        say("resume: every frame is complete; nothing to render")
        return _summary(cfg, store, t0, results=[], failed={}, skipped=cfg.num_frames, dashboard=None,
                        cluster="none (nothing to render)", validation=_validate_run(store, []))
    tc = time.perf_counter()
    _quiet_interrupted_sync()
    conn = cl.connect(cfg.cluster, scheduler=scheduler, workers=workers)
    results: list[dict] = []
    timings: dict = {"start_s": tc - t0, "cluster_start_s": time.perf_counter() - tc}
    try:
        dashboard = conn.dashboard
        gpus = getattr(conn.cluster, "gpus", None)
        say(f"cluster: {conn.kind} at {conn.address}, {conn.n_workers()} worker(s)"
               + (f" (one per GPU: {', '.join(gpus)})" if gpus else ""))
        say(f"dashboard: {dashboard or 'none'}")
        _check_worker_memory(cfg, conn)
        writer, frames = _open_writer(cfg, store, overwrite, say)
        skipped = cfg.num_frames - len(frames)
        tb = time.perf_counter()
        graph = build_graph(cfg, store, frames, functions=functions, generation=generation(store))
        timings["build_graph_s"] = time.perf_counter() - tb
        committer = Committer(writer, check=lock.check if lock is not None else None)
        tr = time.perf_counter()
        results, failed = _execute(conn.client, graph, writer, progress, as_completed,
                                   watch_workers=conn.kind == "local", committer=committer, timings=timings,
                                   on_disk_full=lambda left: store_full(store, "writing frames",
                                                                        space_needed(cfg, store, left)))
        timings.update(commits=committer.commits, commit_latency_s=committer.latencies,
                       frames_s=time.perf_counter() - tr)
    finally:
        tc = time.perf_counter()
        conn.close()
        timings["cluster_close_s"] = time.perf_counter() - tc
    tv = time.perf_counter()
    validation = _validate_run(store, [r["index"] for r in results] + list(failed),
                               {r["index"]: r.get("checked") or [] for r in results})
    timings["validate_s"] = time.perf_counter() - tv
    summary = _summary(cfg, store, t0, results=results, failed=failed, skipped=skipped, dashboard=dashboard,
                       cluster=conn.kind, validation=validation)
    summary["timings"] = _timings(timings, results, summary["render_s"])
    return summary


def _open_writer(cfg: DatasetConfig, store: str, overwrite: bool, say=_silent) -> tuple:
    """The store's writer (created or resumed) and the frames of ``cfg`` it still lacks."""
    from stores.writer import open_or_create
    try:
        writer = open_or_create(store, cfg.store_layout(), cfg.content_dict(), overwrite=overwrite)
    except OSError as e:
        if is_disk_full(e):
            raise store_full(store, "creating the store", space_needed(cfg, store, cfg.num_frames)) from None
        raise
    marked = record_intended_nonfinite(store)
    if marked:
        say(f"resume: {len(marked)} frame(s) of hard cases that make NaN on purpose recorded as such "
            "(frames/nonfinite_expected, newer than this store)")
    todo = set(writer.incomplete_frames())
    frames = [f for f in cfg.frames() if f.index in todo]
    if cfg.num_frames - len(frames):
        say(f"resume: {cfg.num_frames - len(frames)} frame(s) already complete, {len(frames)} to render")
    return writer, frames


def record_intended_nonfinite(store: str) -> list[int]:
    """Record, in a store made before ``frames/nonfinite_expected`` existed (it reads False there), the
    frames whose hard case makes NaN/Inf samples on purpose (``scene_gen.cases.Case.nonfinite``, by their
    ``frames/case``): otherwise the fitness check (``stores.fitness``) flags the NaN the renderer replaced
    in them. The frames marked (none for a store that records it already). Under the run's lock."""
    from scene_gen.cases import nonfinite_expected
    from stores import schema
    root, _ = schema.open_group(store, mode="r+")
    cases = root[schema.meta_path("case")][:]
    flags = root[schema.meta_path("nonfinite_expected")]
    have = np.asarray(flags[:], bool)
    want = np.array([nonfinite_expected(str(c)) for c in cases], bool)
    marked = [int(i) for i in np.nonzero(want & ~have)[0]]
    if marked:
        flags[:] = have | want
    return marked


def _timings(timings: dict, results: list, render_s: float) -> dict:
    """The run's ``timings`` summary: where the run's time went (the command prints it as its ``time:`` line)."""
    lat = timings.pop("commit_latency_s", [])
    tm = {**timings, "commit_latency_mean_s": float(np.mean(lat)) if lat else None,
          "commit_latency_max_s": float(np.max(lat)) if lat else None,
          "write_s": sum(r.get("write_seconds", 0.0) for r in results),
          "load_s": sum(r.get("load_seconds", 0.0) for r in results)}
    return tm


def frames_to_render(cfg: DatasetConfig, store: str) -> list[int] | None:
    """The frames of ``cfg`` a run on ``store`` would render (incomplete, or complete with files missing),
    None when it cannot tell without creating or changing the store (no store yet, or one to grow)."""
    from stores import chunk_files, schema
    from stores.errors import StoreError
    from stores.writer import complete_flags
    if not schema.store_exists(store):
        return None
    try:
        root, layout = schema.open_group(store, mode="r")
    except StoreError:
        return None
    if layout.num_frames != cfg.num_frames or schema.absent_arrays(root):
        return None
    done = complete_flags(root)
    lost = chunk_files.missing_chunks(root, [int(i) for i in np.nonzero(done)[0]])
    return sorted([int(i) for i in np.nonzero(~done)[0]] + list(lost))


def _summary(cfg: DatasetConfig, store: str, t0: float, *, results, failed, skipped, dashboard, cluster,
             validation) -> dict:
    """The run's summary dict (the command prints it as its closing lines)."""
    from stores.writer import complete_flags
    from stores import schema
    elapsed = time.perf_counter() - t0
    render_s = sum(r["render_seconds"] for r in results)
    left = frames_to_render(cfg, store)
    complete = cfg.num_frames - len(left) if left is not None else \
        int(complete_flags(schema.open_group(store, check=False)[0]).sum())
    summary = {
        "store": store, "frames": cfg.num_frames, "complete": complete, "rendered": len(results),
        "skipped": skipped, "failed": failed, "elapsed_s": round(elapsed, 3),
        "render_s": round(render_s, 3), "dashboard": dashboard, "cluster": cluster,
        "validation": validation,
        "ok": not failed and complete == cfg.num_frames and validation.get("ok") is not False,
    }
    return summary


def space_needed(cfg: DatasetConfig, store: str, frames: int) -> int | None:
    """About how many bytes ``frames`` more frames take in ``store``: the bytes a complete frame takes
    there so far (the store's files over its complete frames), else the frame's float32 arrays at the
    default encoding's measured 0.18 of float32 (stores/SCHEMA.md). None when unknown (URLs)."""
    from pipeline.config import frame_bytes
    if "://" in store or frames <= 0:
        return None
    total, done = 0, 0
    try:
        for root, _, files in os.walk(store):
            total += sum(os.path.getsize(os.path.join(root, f)) for f in files)
        from stores import schema
        from stores.writer import complete_flags
        done = int(complete_flags(schema.open_group(store, check=False)[0]).sum())
    except Exception:  # noqa: BLE001 - a store cut short by the full disk: fall back to the estimate
        done = 0
    per_frame = total / done if done else 0.18 * frame_bytes(cfg)
    return int(per_frame * frames)


LOCAL_OVERSUBSCRIBE = 4      # a LocalCluster's worker threads may be at most this many per core


def check_cluster_settings(cfg: DatasetConfig, *, scheduler: str | None = None, workers: int | None = None) -> None:
    """Settings of where the run goes that are wrong whatever the store (ConfigError, exit 2, before the
    lock, the store or a cluster is touched): a ``--scheduler`` that is not a ``scheme://host:port``, a
    dashboard address this machine cannot serve, more LocalCluster workers than
    :data:`LOCAL_OVERSUBSCRIBE` a core."""
    from pipeline.cluster import check_address, check_dashboard, machine_cores
    if scheduler:
        check_address(scheduler)
    elif cfg.cluster.kind == "local" and not cfg.cluster.address:
        check_dashboard(cfg.cluster.dashboard_address)
        n, cores = workers or cfg.cluster.workers, machine_cores()
        if n and n * cfg.cluster.threads_per_worker > LOCAL_OVERSUBSCRIBE * cores:
            raise ConfigError(f"{'--workers' if workers else 'dataset.cluster.workers'} {n} is more than a "
                              f"LocalCluster on this machine's {cores} core(s) can run: each worker is a process "
                              f"of its own; use at most {LOCAL_OVERSUBSCRIBE * cores // cfg.cluster.threads_per_worker}"
                              ", or a cluster (--scheduler, cluster.kind slurm/pbs) for more")


def check_memory_before_start(cfg: DatasetConfig, *, scheduler: str | None = None, workers: int | None = None) -> None:
    """Refuse (ConfigError naming the estimate) a frame that cannot fit in the memory of one worker of
    the cluster this run will start: a LocalCluster of ``workers`` (``--workers``, else the config's,
    else one per core) on this machine, or the configured batch jobs. An existing scheduler
    (``--scheduler``, ``cluster.address``) is checked once connected (``_check_worker_memory``)."""
    c = cfg.cluster
    if scheduler or c.address or c.kind == "scheduler":
        return
    cfg.check_memory(workers=workers if c.kind == "local" else None)


def _check_worker_memory(cfg: DatasetConfig, conn) -> None:
    """A frame must fit in the largest worker's memory limit (workers that report one)."""
    try:
        limits = [int(w.get("memory_limit") or 0)
                  for w in conn.client.scheduler_info(n_workers=-1).get("workers", {}).values()]
    except Exception:  # noqa: BLE001 - an old scheduler without the field: nothing to check
        return
    limits = [m for m in limits if m > 0]
    if limits:
        cfg.check_memory(per_worker=max(limits), where=f"the largest memory_limit of the cluster's {len(limits)} "
                                                        "worker(s)")


LOST_WORKERS_AFTER = 15.0     # seconds a LocalCluster may have no worker before the run gives up on it


class WorkersLostError(PipelineError):
    """Every worker of the run's LocalCluster is gone and none came back (killed, or stopped by a signal
    from outside the run); the frames written so far stay complete, and a re-run resumes."""
    exit_code = 1          # frames were not rendered (as failed frames), not a bad setting


def _watch_workers(client, futures, lost: list, stop, after: float = LOST_WORKERS_AFTER) -> None:
    """Until ``stop`` is set: when the scheduler has had no worker for ``after`` seconds, note it in
    ``lost`` and cancel ``futures`` (so the run stops instead of waiting for workers that will not come)."""
    import time
    since = None
    while not stop.wait(1.0):
        try:
            n = len(client.scheduler_info(n_workers=-1).get("workers", {}))
        except Exception:  # noqa: BLE001 - the scheduler is closing: the main loop will see it
            continue
        if n:
            since = None
            continue
        since = since or time.monotonic()
        if time.monotonic() - since >= after:
            lost.append(time.monotonic() - since)
            client.cancel(futures)
            return


COMMIT_SECONDS = 2.0     # the client commits finished frames (metadata, then status) at most this often


class Committer:
    """The client's side of the v3 write protocol (``stores.writer``): the records of finished frames
    and the errors of failed ones, committed together (``StoreWriter.commit``: metadata, then
    ``status/complete`` last): the first at once, then once :data:`COMMIT_SECONDS` have passed since the
    last commit, and at the end. So a frame costs a share of a few metadata writes, not a write of each value; a run stopped
    between commits leaves those frames incomplete (the resume renders them again). ``latencies``: for
    each committed frame, seconds from its task's end to its commit."""

    def __init__(self, writer, every: float = COMMIT_SECONDS, check=None):
        self.writer, self.every, self.check = writer, every, check     # check: raises if the store was lost
        self.records: dict[int, dict] = {}
        self.failures: dict[int, str] = {}
        self.done_at: dict[int, float] = {}
        self.last = -float("inf")      # the first finished frame is committed at once
        self.latencies: list[float] = []
        self.commits = 0

    def add(self, result: dict) -> None:
        self.records[int(result["index"])] = result["record"]
        self.done_at[int(result["index"])] = float(result.get("done_at") or time.time())

    def fail(self, index: int, text: str) -> None:
        self.failures[int(index)] = text

    def maybe_flush(self) -> None:
        if time.monotonic() - self.last >= self.every:
            self.flush()

    def flush(self) -> None:
        if self.records or self.failures:
            if self.check is not None:
                self.check()                # an S3 lease another run took over: write nothing more
            self.writer.commit(self.records, self.failures)
            now = time.time()
            self.latencies += [now - self.done_at[i] for i in self.records]
            self.commits += 1
            _commit_hook()
        self.records, self.failures, self.done_at = {}, {}, {}
        self.last = time.monotonic()


def _commit_hook() -> None:
    """A seam after each commit of the run, doing nothing: a test replaces it (``tests/procs.pause_at``) to
    kill the run there (some frames complete, the others not, whatever the timing)."""


def _execute(client, graph, writer, progress: bool, as_completed, *, watch_workers: bool = False,
             on_disk_full=None, committer: Committer | None = None,
             timings: dict | None = None) -> tuple[list[dict], dict[int, str]]:
    """Submit ``graph``, wait for every write, commit the frames written (:class:`Committer`) and
    record those that failed. Returns (results, failures). ``watch_workers`` (a LocalCluster's run):
    raise :class:`WorkersLostError` when the cluster has had no worker for :data:`LOST_WORKERS_AFTER`
    seconds, instead of waiting for ever. A write that finds the store's file system full stops the
    run at once (every other write would fail alike): the rest is cancelled and
    ``on_disk_full(frames_left)`` (a ``StoreFullError``) raised; the failed frame stays incomplete, so a
    re-run after freeing space resumes it. So does a write that cannot reach the object store after
    botocore's retries (:mod:`stores.objectstore`). Whatever stops the run, the frames finished before are
    committed first (best effort), so the resume does not render them again."""
    import threading
    by_future = _submit_writes(client, graph, timings)
    commit = committer or Committer(writer)
    results: list[dict] = []
    failed: dict[int, str] = {}
    lost: list = []
    stop = threading.Event()
    if watch_workers and by_future:
        threading.Thread(target=_watch_workers, args=(client, list(by_future), lost, stop),
                         name="watch-workers", daemon=True).start()
    bar = _frames_bar(len(by_future)) if progress and by_future else None

    def full(e):
        return (on_disk_full or (lambda n: e))(len(by_future) - len(results))
    finished = False
    try:
        for fut in as_completed(list(by_future), loop=client.loop):
            if _take(fut, by_future[fut], commit, results, failed, full):
                _flush(commit.maybe_flush, full)
                if bar is not None:
                    bar.update(1)
                    if failed:
                        bar.set_postfix(failed=len(failed))
            fut.release()
        _flush(commit.flush, full)
        finished = True
    finally:
        _wind_down(client, list(by_future), commit, bar, stop, finished)
    if lost:
        raise WorkersLostError(
            f"every worker of the LocalCluster is gone (none for {lost[0]:.0f} s: killed or stopped from outside "
            f"this run); {len(results)} frame(s) were written now and stay complete: run the same command again "
            "to resume")
    return results, failed


def _submit_writes(client, graph, timings: dict | None) -> dict:
    """Submit ``graph`` (its seconds into ``timings["submit_s"]``): the futures of its writes, to their
    frame indices. Only the writes are held: the scheduler then frees each render result once its
    write is done (memory stays bounded by the frames in flight, not the dataset)."""
    ts = time.perf_counter()
    futures = graph.submit(client)
    if timings is not None:
        timings["submit_s"] = time.perf_counter() - ts
    return {futures[k]: idx for idx, k in graph.writes.items()}


def _wind_down(client, futures: list, commit: Committer, bar, stop, finished: bool) -> None:
    """However :func:`_execute`'s loop ended: stop the worker watch, close the progress bar, cancel the
    writes' ``futures`` and, unless every write was taken and committed, commit what finished before
    the stop (best effort: the stop's own error is the one to report)."""
    stop.set()
    if bar is not None:
        bar.close()
    client.cancel(futures)
    if not finished:
        try:
            commit.flush()              # keep what finished before the stop
        except Exception:  # noqa: BLE001 - the stop's own error is the one to report
            pass


def _take(fut, idx: int, commit: Committer, results: list, failed: dict, full) -> bool:
    """One finished write: its result to the committer, or its failure recorded; a full disk or an
    unreachable object store stops the run (every other write would fail alike). False for a write
    cancelled because the run is stopping (its frame stays incomplete)."""
    if fut.status == "finished":
        r = fut.result()
        commit.add(r)
        results.append({k: v for k, v in r.items() if k != "record"})   # the committer holds it
        return True
    if fut.status == "cancelled":
        return False
    exc = fut.exception()
    if is_disk_full(exc):
        raise full(exc)
    if unreachable_cause(exc) is not None:
        raise exc
    text = f"{type(exc).__name__}: {exc}"
    failed[idx] = text
    commit.fail(idx, text)
    return True


def _flush(how, full) -> None:
    """A commit; the store's disk full is the run's StoreFullError (``full(error)``)."""
    try:
        how()
    except OSError as e:
        if not is_disk_full(e):
            raise
        raise full(e) from None


def _frames_bar(n: int):
    from tqdm import tqdm
    return tqdm(total=n, unit="frame", desc="frames", file=sys.stderr, dynamic_ncols=True)


