"""pipeline.cluster: LocalCluster sized to the machine, drjit threads = worker threads, batch job scripts."""
from __future__ import annotations

from pathlib import Path

import pytest

from pipeline import cluster as cl
from pipeline.config import ClusterConfig, load_config

ROOT = Path(__file__).resolve().parent.parent


def _render_threads():
    """In a worker: the thread count the render tasks give drjit, and drjit's pool after applying it."""
    from pipeline import tasks
    from pipeline.variant import mitsuba
    cfg = tasks._render_cfg({"res": [4, 4]})
    mitsuba(threads=cfg.threads)
    import drjit as dr
    return tasks.worker_threads(), cfg.threads, dr.thread_count()


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
    finally:
        conn.close()


def test_workers_override_and_threads_per_worker():
    conn = cl.connect(ClusterConfig(dashboard_address=None, threads_per_worker=2), workers=1)
    try:
        info = conn.client.scheduler_info(n_workers=-1)["workers"]
        assert [w["nthreads"] for w in info.values()] == [2]
    finally:
        conn.close()


@pytest.mark.parametrize("name, needles", [
    ("cluster-slurm.yaml", ["#SBATCH -p normal", "#SBATCH --cpus-per-task=16", "#SBATCH --exclusive",
                            "--nthreads 1", "--nworkers 16"]),
    ("cluster-pbs.yaml", ["#PBS -q gpu", "ngpus=1", "--nthreads 1", "--nworkers 8", "--resources GPU=1"]),
])
def test_jobqueue_examples_make_job_scripts(name, needles):
    pytest.importorskip("dask_jobqueue")
    cfg = load_config(ROOT / "configs" / name)
    jq = dict(cfg.cluster.jobqueue)
    jq["scheduler_options"] = {"host": "127.0.0.1", "dashboard_address": ":0"}    # no sbatch/qsub is called
    c = cl.jobqueue_cluster(cfg.with_cluster(jobqueue=jq).cluster)
    try:
        script = c.job_script()
    finally:
        c.close()
    for n in needles:
        assert n in script, (n, script)


def test_missing_jobqueue_is_a_clear_error(monkeypatch):
    import sys
    monkeypatch.setitem(sys.modules, "dask_jobqueue", None)         # as if it were not installed
    cfg = ClusterConfig(kind="slurm", jobqueue={"cores": 1, "memory": "1GiB"})
    with pytest.raises(cl.ClusterError, match="needs dask-jobqueue: pip install"):
        cl.connect(cfg)
