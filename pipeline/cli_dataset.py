"""``python -m pipeline dataset``: build a dataset from a YAML config on a Dask cluster.

    python -m pipeline dataset --config configs/default.yaml [--out PATH] [--scheduler ADDR] [--workers N]

Order of work (everything that can be wrong is checked before a pixel is rendered):

1. load and validate the config (unknown keys and bad values: exit code 2 with the field named);
2. check an existing store at the target matches the config (else exit code 2);
3. start a LocalCluster sized to the machine, or reach ``--scheduler`` / the configured cluster
   (unreachable: exit code 2), and print the dashboard address;
4. create the store, or open it and list the frames whose ``status/complete`` is not set (resume);
5. submit the graph (``pipeline.graph``) for those frames only, follow it with a progress bar; a frame
   whose task still fails after ``tasks.retries`` retries is recorded in the store (``status/error``)
   and the rest goes on;
6. validate the store and print the summary: store path, frames, elapsed time, dashboard address.

Ctrl-C stops the run; frames already written stay complete and re-running the same command finishes
the others. Exit codes: 0 all frames complete and the store valid, 1 some frames failed or the
validator found problems, 2 bad config / unreachable cluster, 130 interrupted.
"""
from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

from pipeline.config import DatasetConfig, load_config
from pipeline.errors import ConfigError

DEFAULT_CONFIG = "configs/default.yaml"


class StoreMismatchError(ConfigError):
    """The store at the target path was made from a different dataset config."""


def add_arguments(p) -> None:
    p.add_argument("--config", default=DEFAULT_CONFIG, help=f"dataset YAML (default: {DEFAULT_CONFIG})")
    p.add_argument("--out", help="store path or URL (default: the config's out, else $DENOISE_DATA/<name>.zarr)")
    p.add_argument("--scheduler", help="address of a running Dask scheduler (tcp://host:8786) instead of a "
                                       "LocalCluster")
    p.add_argument("--workers", type=int, help="LocalCluster workers (default: one per core) or batch jobs")
    p.add_argument("--no-progress", action="store_true", help="no progress bar (logs only)")
    p.add_argument("--summary-json", help="also write the run summary to this JSON file")
    p.add_argument("--overwrite", action="store_true",
                   help="delete whatever is at the store path first (another store, a store of another config, "
                        "a folder that is not a store) and build from scratch; without it such a path is refused")


def run(args) -> int:
    if args.workers is not None and args.workers < 1:
        raise ConfigError(f"--workers must be an integer >= 1, got {args.workers}")
    cfg = load_config(args.config)
    summary = run_dataset(cfg, out=args.out, scheduler=args.scheduler, workers=args.workers,
                          progress=not args.no_progress, overwrite=args.overwrite)
    if args.summary_json:
        Path(args.summary_json).write_text(json.dumps(summary, indent=2, default=str))
    return 0 if summary["ok"] else 1


def _print(*a) -> None:
    print(*a, flush=True)


def check_existing_store(cfg: DatasetConfig, store: str, *, overwrite: bool = False) -> DatasetConfig:
    """Check what is at ``store`` before anything starts (metadata only: no frame data or completion
    flag is read, so a damaged chunk is left to the resume, which re-renders its frame); returns the
    config to run: ``cfg``, or for a store made before ``clip_ids`` existed, ``cfg`` with
    ``clip_ids: scene_seed`` (its frames keep their split).
    Raises ForeignStoreError for a non-empty folder (or a file) that is not a store,
    StoreMismatchError for a store made from another config (both unless ``overwrite``; a file is
    refused even then)."""
    from stores import schema
    from stores.errors import ForeignStoreError, IncompleteStoreError, StoreCorruptionError
    if "://" not in store and os.path.lexists(store) and not os.path.isdir(store):
        raise ForeignStoreError(f"--out {store} is a file, not a folder; choose another --out")
    found = schema.foreign_entries(store)
    if found:
        if overwrite:
            return cfg
        shown = ", ".join(found[:5]) + (f", ... ({len(found)} entries)" if len(found) > 5 else "")
        raise ForeignStoreError(f"{store} is a non-empty folder that is not a store made by this pipeline "
                                f"(it holds {shown}); nothing was touched: choose another --out, or pass "
                                "--overwrite to delete its contents and build the dataset there")
    if not schema._exists(store):
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
    if have != want:
        keys = sorted(k for k in set(have) | set(want) if have.get(k) != want.get(k))
        raise StoreMismatchError(
            f"the store at {store} was made from a different dataset config (differs in: {', '.join(keys)}); "
            "use another --out, or --overwrite to delete it and start again")
    want_layout = cfg.store_layout()
    if not layout.frame_shape_compatible(want_layout) or layout.num_frames != want_layout.num_frames:
        raise StoreMismatchError(f"the store at {store} has layout {layout.to_dict()}, the config needs "
                                 f"{want_layout.to_dict()}")
    return cfg


def _validate(store: str) -> dict:
    """The store validator's verdict: ``{'ok': bool, 'problems': [...], 'frames_checked': n, 'report': text}``."""
    from stores.validate import validate_store
    rep = validate_store(store)
    problems = list(rep.problems) + [f"frame {f.index}: {p}" for f in rep.frames for p in f.problems]
    return {"ok": bool(rep.ok), "problems": problems, "frames_checked": len(rep.frames), "report": rep.format()}


def run_dataset(cfg: DatasetConfig, *, out: str | None = None, scheduler: str | None = None,
                workers: int | None = None, progress: bool = True, functions=None,
                overwrite: bool = False) -> dict:
    """Build (or resume) the dataset of ``cfg``; returns the summary dict (also printed).

    The run holds the store's writer lock (``stores.lock.StoreLock``) from the first check to the
    summary: a second run on the same store is refused (StoreLockedError naming host, pid and start).
    ``overwrite`` deletes what is at the store path first. ``functions`` replaces the graph's task
    functions (tests inject failures with it).
    """
    from stores.lock import StoreLock
    store = cfg.store_path(out)
    cfg = check_existing_store(cfg, store, overwrite=overwrite)   # before the lock and the cluster: costs nothing
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
            _print(f"lock: took over the lock of a dead run ({describe(lock.took_over)})")
        elif not lock.supported:
            _print("lock: none for URL stores; run one dataset command per store at a time")
        return _run_locked(cfg, store, scheduler=scheduler, workers=workers, progress=progress,
                           functions=functions, overwrite=overwrite)


def _run_locked(cfg: DatasetConfig, store: str, *, scheduler, workers, progress, functions, overwrite) -> dict:
    from distributed import as_completed

    from pipeline import cluster as cl
    from pipeline.graph import build_graph
    from stores.writer import open_or_create

    t0 = time.perf_counter()
    cfg = check_existing_store(cfg, store, overwrite=overwrite)  # again, now that this run holds the lock
    conn = cl.connect(cfg.cluster, scheduler=scheduler, workers=workers)
    try:
        dashboard = conn.dashboard
        _print(f"dataset {cfg.name!r}: {cfg.num_scenes} scenes, {cfg.num_frames} frames at "
               f"{cfg.resolution[0]}x{cfg.resolution[1]} -> {store}")
        _print(f"cluster: {conn.kind} at {conn.address}, {conn.n_workers()} worker(s)")
        _print(f"dashboard: {dashboard or 'none'}")
        _check_worker_memory(cfg, conn)
        writer = open_or_create(store, cfg.store_layout(), cfg.content_dict(), overwrite=overwrite)
        todo = set(writer.incomplete_frames())
        frames = [f for f in cfg.frames() if f.index in todo]
        skipped = cfg.num_frames - len(frames)
        if skipped:
            _print(f"resume: {skipped} frame(s) already complete, {len(frames)} to render")
        graph = build_graph(cfg, store, frames, functions=functions)
        results, failed = _execute(conn.client, graph, writer, progress, as_completed)
        validation = _run_validation(conn.client, store, graph.token)
    except KeyboardInterrupt:
        _print(f"\ninterrupted: complete frames stay in {store}; run the same command again to resume")
        raise
    finally:
        conn.close()
    elapsed = time.perf_counter() - t0
    render_s = sum(r["render_seconds"] for r in results)
    complete = cfg.num_frames - len(writer.incomplete_frames())
    summary = {
        "store": store, "frames": cfg.num_frames, "complete": complete, "rendered": len(results),
        "skipped": skipped, "failed": failed, "elapsed_s": round(elapsed, 3),
        "render_s": round(render_s, 3), "dashboard": dashboard, "cluster": conn.kind,
        "validation": validation,
        "ok": not failed and complete == cfg.num_frames and validation.get("ok") is not False,
    }
    _print("")
    _print(f"store:      {store}")
    _print(f"frames:     {complete}/{cfg.num_frames} complete ({len(results)} rendered now, {skipped} skipped, "
           f"{len(failed)} failed)")
    for idx, err in sorted(failed.items()):
        _print(f"  frame {idx} failed: {err}")
    _print(f"elapsed:    {elapsed:.1f} s (render time {render_s:.1f} s summed over tasks)")
    _print(f"dashboard:  {dashboard or 'none'}")
    v = validation
    _print(f"validation: {'ok' if v.get('ok') else ('not run' if v.get('ok') is None else 'PROBLEMS')}"
           + ("".join(f"\n  {p}" for p in v.get("problems", [])[:20]) if not v.get("ok") else ""))
    return summary


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


def _execute(client, graph, writer, progress: bool, as_completed) -> tuple[list[dict], dict[int, str]]:
    """Submit ``graph``, wait for every write, record frames that failed. Returns (results, failures)."""
    futures = graph.submit(client)
    by_future = {futures[k]: idx for idx, k in graph.writes.items()}
    # Hold only the writes: the scheduler then frees each render result once its write is done
    # (memory stays bounded by the frames in flight, not the dataset).
    del futures
    results: list[dict] = []
    failed: dict[int, str] = {}
    bar = None
    if progress and by_future:
        from tqdm import tqdm
        bar = tqdm(total=len(by_future), unit="frame", desc="frames", file=sys.stderr, dynamic_ncols=True)
    try:
        for fut in as_completed(list(by_future), loop=client.loop):
            idx = by_future[fut]
            if fut.status == "finished":
                results.append(fut.result())
            else:
                exc = fut.exception()
                text = f"{type(exc).__name__}: {exc}"
                failed[idx] = text
                writer.mark_failed(idx, text)
            if bar is not None:
                bar.update(1)
                if failed:
                    bar.set_postfix(failed=len(failed))
            fut.release()
    finally:
        if bar is not None:
            bar.close()
        client.cancel(list(by_future))
    return results, failed


def _run_validation(client, store: str, token: str) -> dict:
    """Run the validator as a task on the cluster (it reads the whole store)."""
    fut = client.submit(_validate, store, key=f"validate-store@{token}", pure=False)
    try:
        return fut.result()
    except Exception as e:  # noqa: BLE001 - the validator itself broke: say so in the summary
        return {"ok": False, "problems": [f"validator failed: {type(e).__name__}: {e}"]}
