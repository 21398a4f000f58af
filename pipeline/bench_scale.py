"""What a frame costs as the dataset grows (``python -m pipeline bench --only scale [--frames 100 1000 10000]``).

``configs/scale.yaml``'s cheapest frames (8x8 pixels, 1 spp, one sample layer, 16-spp references, two
long clips, so kernels compile once a scene) at each size F, on a real ``dask scheduler`` process and
two single-threaded ``dask worker`` processes (so the scheduler's memory is its own, apart from the
client's). Per frame (milliseconds unless said), at each size:

- ``dataset``: the whole ``pipeline dataset`` run's wall time; ``render``: the render tasks' time;
  ``write``: the write tasks' time (image shards);
- ``graph_build`` and ``graph_submit``: building the graph and handing it to the scheduler;
- ``commit``: a write task's end until its frame is committed (metadata, then ``status/complete``);
- ``scheduler_kib`` and ``client_kib``: the peak growth of each process's memory during the run, KiB;
- ``validate``: ``validate_store`` of the whole store (every frame read);
- ``rerun``: the same command on the complete store (it must render nothing; target under 15 s in all
  at 10,000 frames);
- ``export10``: ``export`` of ten frames (exr), per exported frame;
- ``open_zarr``: ``xarray.open_zarr`` of every group;
- ``dataset_<kind>``: the store's side of building the training dataset of each input kind on the train
  split (its frames or clips, the fitness check of every frame it uses) and of its first batch, per
  frame of the split;
- ``files`` and ``bytes``: the store's files and bytes per frame.

The table prints each stage at each size and the ratio of the largest size's per-frame cost to the
smallest's (target: within 1.5x). :func:`paper_graphs` builds and submits (with no worker, so nothing
renders) the graphs of ``configs/layer-paper.yaml`` and ``configs/temporal-paper.yaml`` and states
their time and memory.
"""
from __future__ import annotations

import importlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SCALE = ROOT / "configs" / "scale.yaml"
DEFAULT_FRAMES = (100, 1000, 10000)
STAGES = ("dataset", "render", "write", "graph_build", "graph_submit", "commit", "scheduler_kib", "client_kib",
          "validate", "rerun", "export10", "open_zarr", "dataset_samples", "dataset_pixels", "dataset_clips",
          "dataset_sampled-layers", "files", "bytes")


def scale_config(frames: int):
    """``configs/scale.yaml`` with its two clips sized to ``frames`` frames in all."""
    from pipeline.config import SceneGroup, load_config
    cfg = load_config(SCALE)
    a = frames // 2
    return cfg.with_overrides(scenes=(SceneGroup("indoor", 1, a), SceneGroup("outdoor", 1, frames - a)))


class _Peak(threading.Thread):
    """Samples the RSS of some processes every 0.2 s; ``peak[pid]`` the largest seen."""

    def __init__(self, pids):
        super().__init__(daemon=True)
        import psutil
        self.procs = {p: psutil.Process(p) for p in pids}
        self.peak = {p: pr.memory_info().rss for p, pr in self.procs.items()}
        self.base = dict(self.peak)
        self.stop = threading.Event()

    def run(self):
        while not self.stop.wait(0.2):
            for p, pr in self.procs.items():
                try:
                    self.peak[p] = max(self.peak[p], pr.memory_info().rss)
                except Exception:  # noqa: BLE001 - the process ended
                    pass


def _cluster(tmp: Path, workers: int = 2):
    """A ``dask scheduler`` and ``workers`` single-threaded ``dask worker`` processes on 127.0.0.1."""
    dask = str(Path(sys.executable).parent / "dask")
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    sf = tmp / "scheduler.json"
    sf.unlink(missing_ok=True)                  # a file of an earlier scheduler would name its address
    procs = [subprocess.Popen([dask, "scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                               "--scheduler-file", str(sf)], env=env, cwd=ROOT, start_new_session=True,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    t0 = time.monotonic()
    while not sf.exists() and time.monotonic() - t0 < 60:
        time.sleep(0.2)
    address = json.loads(sf.read_text())["address"]
    for i in range(workers):
        procs.append(subprocess.Popen([dask, "worker", address, "--nthreads", "1", "--no-nanny", "--no-dashboard",
                                       "--host", "127.0.0.1", "--name", f"scale-{i}"], env=env, cwd=ROOT,
                                      start_new_session=True, stdout=subprocess.DEVNULL,
                                      stderr=subprocess.DEVNULL))
    return address, procs


def _stop(procs) -> None:
    import signal
    for p in procs:
        try:
            os.killpg(p.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        p.wait(timeout=30)


def _wait_workers(address: str, n: int) -> None:
    from distributed import Client
    with Client(address, set_as_default=False, timeout=60) as c:
        c.wait_for_workers(n, timeout=120)


# what a training dataset of each input kind reads of a store (``training.inputs``: the kinds' arrays)
KIND_ARRAYS = {"samples": ("inputs/radiance", "inputs/features"), "pixels": ("inputs/radiance", "inputs/features"),
               "clips": ("inputs/radiance", "inputs/features"), "sampled-layers": ("layers/radiance",)}


def _dataset_stage(store: str, kind: str) -> float:
    """Seconds for the store's side of building ``kind``'s training dataset on the train split (the same
    calls ``training.datasets`` makes: the split's frames or clips, the fitness screen of every frame it
    uses, ``stores.fitness``) and reading its first batch (4 crops of 8x8). The pipeline does not import
    training; ``python -m training bench`` times the models."""
    from stores.reader import open_store
    t = time.perf_counter()
    st = open_store(store)
    frames = ([i for c in st.clips("train").values() for i in c] if kind == "clips"
              else st.frames_in_split("train"))
    st.check_frames(sorted(set(frames) | set(st.incomplete_frames())))
    for i in frames[:4]:
        for path in KIND_ARRAYS[kind]:
            st.read_array(path, i, (0, 0, 8, 8))
    return time.perf_counter() - t


def _run_with_peaks(cfg, store: str, tmp: Path) -> tuple[dict, dict]:
    """``run_dataset`` of ``cfg`` into ``store`` on a fresh :func:`_cluster` (stopped after), the peak
    memory growth of its scheduler and of this process sampled throughout: (the run's summary,
    ``{"scheduler_kib", "client_kib"}``)."""
    from pipeline.dataset import run_dataset
    address, procs = _cluster(tmp)
    try:
        _wait_workers(address, 2)
        importlib.import_module("psutil")      # the sampler's, imported before it starts
        peak = _Peak([procs[0].pid, os.getpid()])
        peak.start()
        s = run_dataset(cfg, out=store, scheduler=address)
        peak.stop.set()
        peak.join()
    finally:
        _stop(procs)
    return s, {"scheduler_kib": (peak.peak[procs[0].pid] - peak.base[procs[0].pid]) / 1024,
               "client_kib": (peak.peak[os.getpid()] - peak.base[os.getpid()]) / 1024}


def _validate_and_rerun(cfg, store: str) -> dict:
    """Seconds of ``validate_store`` of the complete store (it must pass) and of the same run again on it
    (it must render nothing)."""
    from pipeline.dataset import run_dataset
    from stores.validate import validate_store
    out = {}
    t0 = time.perf_counter()
    rep = validate_store(store)
    out["validate"] = time.perf_counter() - t0
    assert rep.ok, rep.format()[-2000:]
    t0 = time.perf_counter()
    again = run_dataset(cfg, out=store)
    out["rerun"] = time.perf_counter() - t0
    assert again["rendered"] == 0 and again["ok"], again
    return out


def _read_stages(store: str, frames: int, tmp: Path) -> tuple[dict, int]:
    """Seconds a frame of the stages that read the complete store (``export10``, ``open_zarr`` in all,
    ``dataset_<kind>``), and the train split's frames."""
    import xarray as xr

    from stores.export import export
    from stores.reader import open_store
    from stores.schema import GROUPS
    out = {}
    n_exp = min(10, frames)
    t0 = time.perf_counter()
    export(store, f"0-{n_exp - 1}", "exr", str(tmp / f"export-{frames}"))
    out["export10"] = (time.perf_counter() - t0) * frames / n_exp   # per exported frame after the division
    t0 = time.perf_counter()
    for g in GROUPS:
        xr.open_zarr(store, group=g)
    out["open_zarr"] = time.perf_counter() - t0
    train = len(open_store(store).frames_in_split("train"))
    for kind in ("samples", "pixels", "clips", "sampled-layers"):
        out[f"dataset_{kind}"] = _dataset_stage(store, kind) * frames / max(1, train)
    return out, train


def _files_and_bytes(store: str) -> tuple[int, int]:
    """The files under ``store`` and their bytes."""
    files = nbytes = 0
    for r, _, fs in os.walk(store):
        files += len(fs)
        nbytes += sum(os.path.getsize(os.path.join(r, f)) for f in fs)
    return files, nbytes


def measure(frames: int, tmp: Path) -> dict:
    """Every stage's cost at ``frames`` frames (the module docstring): ``{stage: value per frame}`` plus
    ``_abs`` (whole-run figures: seconds, sizes)."""
    # imported before the run, so the client's memory growth is the run's own
    for name in ("xarray", "pipeline.dataset", "stores.export", "stores.reader", "stores.schema", "stores.validate"):
        importlib.import_module(name)
    cfg = scale_config(frames)
    store = str(tmp / f"scale-{frames}.zarr")
    s, kib = _run_with_peaks(cfg, store, tmp)
    assert s["ok"] and s["complete"] == frames, s
    t = s["timings"]
    out = {"dataset": s["elapsed_s"], "render": s["render_s"], "write": t["write_s"],
           "graph_build": t["build_graph_s"], "graph_submit": t["submit_s"],
           "commit": t["commit_latency_mean_s"] * frames,       # per frame below: its mean latency
           "scheduler_kib": kib["scheduler_kib"], "client_kib": kib["client_kib"]}
    out.update(_validate_and_rerun(cfg, store))
    reads, train = _read_stages(store, frames, tmp)
    out.update(reads)
    files, nbytes = _files_and_bytes(store)
    per = {k: 1e3 * v / frames for k, v in out.items()}
    per["scheduler_kib"], per["client_kib"] = out["scheduler_kib"] / frames, out["client_kib"] / frames
    per["files"], per["bytes"] = files / frames, nbytes / frames
    per["_abs"] = {"frames": frames, "dataset_s": s["elapsed_s"], "rerun_s": out["rerun"], "validate_s": out["validate"],
                   "files": files, "bytes": nbytes, "commits": t["commits"],
                   "commit_latency_max_s": t["commit_latency_max_s"], "train_frames": train}
    shutil.rmtree(store, ignore_errors=True)
    shutil.rmtree(tmp / f"export-{frames}", ignore_errors=True)
    return per


def paper_graphs(names=("layer-paper", "temporal-paper")) -> dict:
    """Build and submit each paper config's whole graph to a scheduler with no worker (nothing renders),
    then cancel it: nodes, build and submit seconds, scheduler and client memory growth."""
    import psutil
    from distributed import Client

    from pipeline.config import load_config
    from pipeline.graph import build_graph
    out = {}
    with tempfile.TemporaryDirectory(prefix="bench-graph-") as d:
        address, procs = _cluster(Path(d), workers=0)
        try:
            sched = psutil.Process(procs[0].pid)
            with Client(address, set_as_default=False, timeout=60) as c:
                for name in names:
                    cfg = load_config(ROOT / "configs" / f"{name}.yaml")
                    m0, c0 = sched.memory_info().rss, psutil.Process().memory_info().rss
                    t0 = time.perf_counter()
                    g = build_graph(cfg, f"{d}/{name}.zarr")
                    t1 = time.perf_counter()
                    futs = g.submit(c)
                    c.sync(c.scheduler.identity)               # the scheduler has taken every task
                    t2 = time.perf_counter()
                    m1, c1 = sched.memory_info().rss, psutil.Process().memory_info().rss
                    c.cancel(list(futs.values()))
                    del futs
                    out[name] = {"frames": cfg.num_frames, "tasks": len(g.nodes), "build_s": t1 - t0,
                                 "submit_s": t2 - t1, "scheduler_mib": (m1 - m0) / 2 ** 20,
                                 "client_mib": (c1 - c0) / 2 ** 20}
        finally:
            _stop(procs)
    return out


def run(frames=DEFAULT_FRAMES, graphs: bool = True, verbose: bool = True) -> dict:
    """Measure every size of ``frames``; returns ``{stage: {F: per-frame value}}`` (the ``--json`` file of
    ``--only scale``), with ``_abs`` (whole-run figures by size) and ``_paper_graphs``."""
    frames = sorted(int(f) for f in frames)
    table: dict = {st: {} for st in STAGES}
    absolute = {}
    with tempfile.TemporaryDirectory(prefix="bench-scale-") as d:
        for n in frames:
            if verbose:
                print(f"scale: {n} frames ...", flush=True)
            per = measure(n, Path(d))
            absolute[str(n)] = per.pop("_abs")
            for st in STAGES:
                table[st][str(n)] = per[st]
            if verbose:
                a = absolute[str(n)]
                print(f"  dataset {a['dataset_s']:.1f} s, re-run {a['rerun_s']:.2f} s, validate {a['validate_s']:.1f} s, "
                      f"{a['files']} files, {a['bytes'] / 2 ** 20:.1f} MiB", flush=True)
    res = dict(table)
    res["_abs"] = absolute
    if graphs:
        res["_paper_graphs"] = paper_graphs()
    if verbose:
        print(format_table(res))
    return res


UNITS = {"scheduler_kib": "KiB", "client_kib": "KiB", "files": "files", "bytes": "bytes"}


def format_table(res: dict) -> str:
    sizes = sorted({int(k) for st in STAGES for k in res.get(st, {})})
    head = "| stage (per frame) | " + " | ".join(f"{n:,}" for n in sizes) + f" | {sizes[-1]:,} / {sizes[0]:,} |"
    lines = [head, "|---|" + "---|" * (len(sizes) + 1)]
    for st in STAGES:
        row = res.get(st, {})
        vals = [row.get(str(n)) for n in sizes]
        unit = UNITS.get(st, "ms")
        cells = [("-" if v is None else (f"{v:.3g}" if unit != "bytes" else f"{v:,.0f}")) for v in vals]
        a, b = vals[0], vals[-1]
        ratio = f"{b / a:.2f}x" if a and b is not None and a > 0 else "-"
        lines.append(f"| {st} ({unit}) | " + " | ".join(cells) + f" | {ratio} |")
    for n, a in (res.get("_abs") or {}).items():
        lines.append(f"\n{int(n):,} frames: dataset {a['dataset_s']:.1f} s, re-run on the complete store "
                     f"{a['rerun_s']:.2f} s, validate {a['validate_s']:.1f} s, {a['files']:,} files, "
                     f"{a['bytes'] / 2 ** 20:.1f} MiB, {a['commits']} commits (longest wait "
                     f"{a['commit_latency_max_s']:.2f} s)")
    for name, g in (res.get("_paper_graphs") or {}).items():
        lines.append(f"{name}: {g['frames']:,} frames, {g['tasks']:,} tasks, graph built in {g['build_s']:.2f} s, "
                     f"submitted in {g['submit_s']:.2f} s; scheduler +{g['scheduler_mib']:.0f} MiB, "
                     f"client +{g['client_mib']:.0f} MiB")
    return "\n".join(lines)


if __name__ == "__main__":  # pragma: no cover
    print(json.dumps(run(), indent=1, default=str))
