"""pipeline.cluster: LocalCluster sized to the machine, drjit threads = worker threads, batch job scripts."""
from __future__ import annotations

from pathlib import Path

import pytest

from pipeline import cluster as cl, jobs
from pipeline.config import ClusterConfig, load_config

ROOT = Path(__file__).resolve().parent.parent


def _render_threads():
    """In a worker: the thread count the render tasks give drjit, and drjit's pool after applying it."""
    from pipeline import tasks
    from core.variant import mitsuba
    cfg = tasks._render_cfg({"res": [4, 4]})
    mitsuba(threads=cfg.threads)
    import drjit as dr
    return tasks.worker_threads(), cfg.threads, dr.thread_count()


def _a_temporary_array_is_mmapped() -> bool:
    """In a worker: whether glibc serves a 2 MiB allocation (a scene's temporary numpy arrays) by mmap,
    faulting its pages in afresh, rather than from the heap (``pipeline.worker_init.MALLOC_ENV``). Dask's
    MALLOC_TRIM_THRESHOLD_ alone pins the mmap threshold at 128 KiB for good (glibc's default starts there
    too, and rises once it frees such a block)."""
    import ctypes

    import numpy as np

    class MallInfo2(ctypes.Structure):
        _fields_ = [(n, ctypes.c_size_t) for n in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks",
                                                   "fsmblks", "uordblks", "fordblks", "keepcost")]
    libc = ctypes.CDLL("libc.so.6")
    libc.mallinfo2.restype = MallInfo2
    before = libc.mallinfo2().hblks
    a = np.empty(1 << 18)               # 2 MiB
    mapped = libc.mallinfo2().hblks > before
    del a
    return mapped


def test_local_cluster_is_sized_to_the_machine_and_drjit_to_the_worker():
    conn = cl.connect(ClusterConfig(dashboard_address=":0"))
    try:
        info = conn.client.scheduler_info(n_workers=-1)["workers"]
        assert conn.kind == "local" and len(info) == cl.machine_cores()
        assert all(w["nthreads"] == 1 for w in info.values())
        assert conn.dashboard.startswith("http://") and conn.dashboard.endswith("/status")
        assert conn.address.startswith("tcp://127.0.0.1:")
        got = [conn.client.submit(_render_threads, workers=[w], pure=False).result() for w in info]
        assert set(got) == {(1, 1, 1)}          # one drjit thread per single-threaded worker
        # glibc's allocator as worker_init sets it, not as the nanny's MALLOC_TRIM_THRESHOLD_ leaves it
        assert not any(conn.client.run(_a_temporary_array_is_mmapped).values())
    finally:
        conn.close()


def _http_port(dask_scheduler):
    return dask_scheduler.http_server.port


def test_workers_override_and_threads_per_worker():
    conn = cl.connect(ClusterConfig(dashboard_address=None, threads_per_worker=2), workers=1)
    try:
        info = conn.client.scheduler_info(n_workers=-1)["workers"]
        assert [w["nthreads"] for w in info.values()] == [2]
        # null: no dashboard, and the scheduler's own HTTP routes stay off the dashboard's port
        assert conn.dashboard is None
        assert conn.client.run_on_scheduler(_http_port) not in (0, 8787)
    finally:
        conn.close()


@pytest.mark.parametrize("name, needles", [
    ("cluster-slurm.yaml", ["#SBATCH -p normal", "#SBATCH --cpus-per-task=16", "#SBATCH --exclusive",
                            "--nthreads 1", "--nworkers 16"]),
    ("cluster-pbs.yaml", ["#PBS -q gpu", "ngpus=1", "--nthreads 1", "--resources GPU=1",
                          "export DENOISE_GPU_PER_WORKER=1"]),
])
def test_jobqueue_examples_make_job_scripts(name, needles):
    pytest.importorskip("dask_jobqueue")
    cfg = load_config(ROOT / "configs" / name)
    jq = dict(cfg.cluster.jobqueue)
    jq["scheduler_options"] = {"host": "127.0.0.1", "dashboard_address": ":0"}    # no sbatch/qsub is called
    c = jobs.jobqueue_cluster(cfg.with_cluster(jobqueue=jq).cluster)
    try:
        script = c.job_script()
    finally:
        c.close()
    for n in needles + ["export MALLOC_MMAP_THRESHOLD_=33554432", "export MALLOC_TRIM_THRESHOLD_=67108864"]:
        assert n in script, (n, script)


def test_a_batch_cluster_without_a_dashboard_leaves_its_port_alone():
    pytest.importorskip("dask_jobqueue")
    cfg = load_config(ROOT / "configs" / "cluster-slurm.yaml")
    jq = {**cfg.cluster.jobqueue, "scheduler_options": {"host": "127.0.0.1"}}    # no sbatch is called
    c = jobs.jobqueue_cluster(cfg.with_cluster(jobqueue=jq, dashboard_address=None).cluster)
    try:
        assert c.scheduler.http_server.port not in (0, 8787)
        assert cl._shows_dashboard(c.scheduler_spec["options"]) is False
    finally:
        c.close()
    c = jobs.jobqueue_cluster(cfg.with_cluster(jobqueue={**jq, "scheduler_options": {
        "host": "127.0.0.1", "dashboard_address": "127.0.0.1:0"}}).cluster)
    try:
        assert cl._shows_dashboard(c.scheduler_spec["options"]) is True
    finally:
        c.close()


def test_missing_jobqueue_is_a_clear_error(monkeypatch):
    import sys
    monkeypatch.setitem(sys.modules, "dask_jobqueue", None)         # as if it were not installed
    cfg = ClusterConfig(kind="slurm", jobqueue={"cores": 1, "memory": "1GiB"})
    with pytest.raises(cl.ClusterError, match="needs dask-jobqueue: pip install"):
        cl.connect(cfg)


# ---- GPUs: one worker each (cluster.gpus) --------------------------------------------------------------
def test_the_cluster_asks_core_variant_for_gpus():
    """One place detects GPUs (core.variant.visible_gpus, tests/test_variant.py); render_gpus asks it."""
    import core.variant
    assert cl.visible_gpus is core.variant.visible_gpus


@pytest.mark.parametrize("gpus, want", [("auto", ["0", "1"]), (None, []), (0, []), (1, ["0"]), ([1], ["1"]),
                                        ([1, 0], ["1", "0"])])
def test_render_gpus_follow_the_config(monkeypatch, gpus, want):
    monkeypatch.setattr(cl, "visible_gpus", lambda: ["0", "1"])
    assert cl.render_gpus(ClusterConfig(gpus=gpus)) == want


@pytest.mark.parametrize("gpus", [3, [2], [0, 5]])
def test_more_gpus_than_the_machine_shows_is_a_config_error(monkeypatch, gpus):
    from pipeline.errors import ConfigError
    monkeypatch.setattr(cl, "visible_gpus", lambda: ["0", "1"])
    with pytest.raises(ConfigError, match=r"dataset.cluster.gpus is .* but this machine shows 2 GPU\(s\) \(0, 1"):
        cl.render_gpus(ClusterConfig(gpus=gpus))


@pytest.mark.parametrize("gpus", [-1, "all", [0, 0], [], [True], 2.0])
def test_bad_gpus_settings_are_refused(gpus):
    from pipeline.errors import ConfigError
    with pytest.raises(ConfigError, match="dataset.cluster.gpus"):
        ClusterConfig(gpus=gpus).validate()


def _gpu_env():
    import os
    return os.environ.get("CUDA_VISIBLE_DEVICES")


def test_a_gpu_machine_gets_one_worker_per_gpu_each_seeing_its_own(monkeypatch):
    """Two pretended GPUs (the workers render with the LLVM backend here: no driver): two workers, each
    with its own CUDA_VISIBLE_DEVICES and the GPU resource; a task asking for a GPU runs on them; a
    worker that is replaced takes the GPU no other worker holds."""
    monkeypatch.setattr(cl, "visible_gpus", lambda: ["0", "1"])
    conn = cl.connect(ClusterConfig(dashboard_address=None))
    try:
        info = conn.client.scheduler_info(n_workers=-1)["workers"]
        assert len(info) == 2 and all(w["resources"] == {"GPU": 1} for w in info.values())
        seen = conn.client.run(_gpu_env)
        assert sorted(seen.values()) == ["0", "1"]
        assert conn.client.submit(_gpu_env, resources={"GPU": 1}, pure=False).result() in ("0", "1")
        assert conn.cluster.gpus == ["0", "1"]
        # a worker that goes (scaled down: its spec and process) is replaced by one on the GPU it held
        import time
        conn.cluster.scale(1)
        t0 = time.monotonic()
        while len(conn.client.scheduler_info(n_workers=-1)["workers"]) > 1 and time.monotonic() - t0 < 60:
            time.sleep(0.1)
        left = list(conn.client.run(_gpu_env).values())
        assert len(left) == 1
        conn.cluster.scale(2)
        conn.client.wait_for_workers(2, timeout=60)
        now = conn.client.run(_gpu_env)
        assert sorted(now.values()) == ["0", "1"] and not set(now) & set(seen) - {a for a, g in seen.items() if g in left}
        conn.cluster.scale(3)                                  # more workers than GPUs: still one a GPU
        assert len(conn.cluster.worker_spec) == 2
        with pytest.raises(cl.ClusterError, match="one worker a GPU"):
            conn.cluster.new_worker_spec()
    finally:
        conn.close()


def test_the_dashboards_own_errors_stay_out_of_the_terminal(capsys):
    """A browser tab that drops its websocket mid-message makes Bokeh's server raise (the AssertionError of
    ``ServerConnection.session`` on a detached session), logged through tornado with its traceback: left
    out once a cluster is connected; tornado's other errors and distributed's own records still print."""
    import logging
    import sys

    from bokeh.server.connection import ServerConnection

    from pipeline.cluster import quiet_dashboard
    quiet_dashboard()
    handler = logging.StreamHandler(sys.stderr)
    app = logging.getLogger("tornado.application")
    app.addHandler(handler)
    try:
        conn = ServerConnection.__new__(ServerConnection)
        conn._session = None
        try:
            conn.session                                 # what a closed tab's message meets
        except AssertionError:
            app.error("Exception in callback", exc_info=True)
            logging.getLogger("bokeh.server.views.ws").error("Handler or its work threw", exc_info=True)
        try:
            raise KeyError("the run's own")
        except KeyError:
            app.error("Uncaught exception in the scheduler", exc_info=True)
    finally:
        app.removeHandler(handler)
    err = capsys.readouterr().err
    assert "AssertionError" not in err and "Handler or its work" not in err
    assert "Uncaught exception in the scheduler" in err and "the run's own" in err
