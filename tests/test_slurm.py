"""SLURM through dask-jobqueue (``cluster.kind: slurm``): what a worker needs reaches its job script, and on
a real one-node SLURM cluster (``scripts/local-slurm.sh``, started here when it is not up) the smoke set
renders through ``sbatch`` jobs, survives cancelled jobs, a job reaching its walltime and a killed client,
and equals a LocalCluster run of the same content array for array.

The job-script tests need no SLURM. The cluster tests need root (they install slurm-wlm and munge with
apt-get when missing, and start the daemons); where that is impossible they are skipped with
local-slurm.sh's reason (``-ra`` prints it). Test processes of one session (pytest-xdist) share the
cluster: the first starts it, the last one out stops it if a test started it, and each test cancels only
its own jobs (a job name of its own).
"""
from __future__ import annotations

import fcntl
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
import uuid
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
import yaml

from procs import kill_group, pause_at, python_m, setting

ROOT = Path(__file__).resolve().parent.parent
SCRIPT = ROOT / "scripts" / "local-slurm.sh"
SMOKE = ROOT / "configs" / "smoke.yaml"
SMOKE_SLURM = ROOT / "configs" / "smoke-slurm.yaml"
PY = sys.executable
# One test process runs them all (make test: --dist loadgroup): the cluster has this machine's cores, and
# a test that needs both its jobs running would wait on another test's jobs holding them.
pytestmark = pytest.mark.xdist_group("slurm")
TIMING = {"frames/render_seconds"}           # a clock reading, not data
KEEPER_EVERY = 2.0                           # pipeline.jobs.JobKeeper's check interval (s)


def _env() -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    env["PYTHONUNBUFFERED"] = "1"
    return env


def _script_of(cluster) -> str:
    """The job script of ``jobqueue_cluster(cluster)`` (its scheduler on 127.0.0.1; nothing is submitted)."""
    from pipeline.jobs import jobqueue_cluster
    c = jobqueue_cluster(cluster)
    try:
        return c.job_script()
    finally:
        c.close()


def _cluster(**kw):
    from pipeline.config import ClusterConfig
    jq = {"scheduler_options": {"host": "127.0.0.1"}, **kw.pop("jobqueue")}
    return ClusterConfig(kind=kw.pop("kind", "slurm"), dashboard_address=None, jobqueue=jq, **kw)


# ---- the job script (no SLURM needed) ----------------------------------------------------------------
def test_smoke_slurm_has_the_smoke_content_and_a_job_script_with_what_a_worker_needs():
    pytest.importorskip("dask_jobqueue")
    from pipeline.config import load_config
    from core.variant import find_libllvm
    cfg = load_config(SMOKE_SLURM)
    assert cfg.content_dict() == load_config(SMOKE).content_dict()      # its store equals smoke.yaml's
    jq = dict(cfg.cluster.jobqueue, log_directory=None)
    script = _script_of(cfg.with_cluster(jobqueue=jq, dashboard_address=None).cluster)
    lines = script.splitlines()
    for needle in ["#SBATCH -J denoise-smoke", "#SBATCH -n 1", "#SBATCH --cpus-per-task=1", "#SBATCH --mem=3G",
                   "#SBATCH -t 00:30:00", f"cd {os.getcwd()}", "export OMP_NUM_THREADS=1",
                   "export MKL_NUM_THREADS=1", "export OPENBLAS_NUM_THREADS=1"]:
        assert needle in lines, (needle, script)
    worker = lines[-1]
    assert worker.startswith(f"{ROOT}/.venv/bin/python -m distributed.cli.dask_worker tcp://127.0.0.1:"), script
    for needle in ["--nthreads 1", "--memory-limit 3.00GiB", "--death-timeout 30", "--preload pipeline.worker_init"]:
        assert needle in worker, (needle, worker)
    assert "--nworkers" not in worker                       # one worker a job
    lib = find_libllvm()
    if lib:
        assert f"if [ -f {lib} ]; then export DRJIT_LIBLLVM_PATH={lib}; fi" in lines, script
    assert script.index("export OMP_NUM_THREADS") < script.index(worker)


def test_threads_memory_resources_python_and_prologue_reach_the_job_script(monkeypatch):
    pytest.importorskip("dask_jobqueue")
    monkeypatch.setenv("MI_VARIANT", "llvm_ad_rgb")
    c = _cluster(threads_per_worker=2, jobqueue={
        "cores": 4, "memory": "8GiB", "resources": {"SCRATCH": 1}, "python": ".venv/bin/python", "queue": "gpu",
        "job_script_prologue": ["module load llvm", "export OMP_NUM_THREADS=2"]})
    script = _script_of(c)
    lines = script.splitlines()
    for needle in ["#SBATCH -p gpu", "#SBATCH --cpus-per-task=4", "#SBATCH --mem=8G", "export MI_VARIANT=llvm_ad_rgb",
                   "module load llvm"]:
        assert needle in lines, (needle, script)
    worker = lines[-1]
    assert worker.startswith(f"{ROOT}/.venv/bin/python -m distributed.cli.dask_worker ")   # from the checkout
    for needle in ["--nthreads 2", "--nworkers 2", "--memory-limit 4.00GiB", "--resources SCRATCH=1",
                   "--preload pipeline.worker_init"]:
        assert needle in worker, (needle, worker)
    # the config's own lines come after ours, so they may override them
    assert lines.index("export OMP_NUM_THREADS=1") < lines.index("module load llvm") \
        < lines.index("export OMP_NUM_THREADS=2") < lines.index(worker)

    pbs = _script_of(_cluster(kind="pbs", jobqueue={"cores": 2, "memory": "4GiB", "resources": {"MEM": 2.5},
                                                    "gpus_per_job": 2, "resource_spec": "select=1:ncpus=2:ngpus=2"}))
    assert "#PBS -l select=1:ncpus=2:ngpus=2" in pbs and "--resources MEM=2.5,GPU=1" in pbs
    assert "--nworkers 2" in pbs and "--nthreads 1" in pbs and "export OPENBLAS_NUM_THREADS=1" in pbs
    assert f"{PY} -m distributed.cli.dask_worker" in pbs              # python defaults to this venv's


def test_no_two_workers_of_a_job_share_a_gpu():
    """One worker per GPU in every case: a job whose workers each claim a GPU without gpus_per_job, or
    whose own directives ask for fewer GPUs than its workers, is refused before anything is submitted;
    a worker whose job sees fewer GPUs than it has workers does not start (pretended devices)."""
    pytest.importorskip("dask_jobqueue")
    from pipeline.errors import ConfigError
    from pipeline.worker_init import GPUShortageError, gpu_for_worker
    with pytest.raises(ConfigError, match="each of a job's 2 workers a GPU.*gpus_per_job: 2"):
        _script_of(_cluster(jobqueue={"cores": 2, "memory": "4GiB", "resources": {"GPU": 1}}))
    with pytest.raises(ConfigError, match="each of a job's 2 workers a GPU"):
        _script_of(_cluster(jobqueue={"cores": 2, "memory": "4GiB", "worker_extra_args": ["--resources", "GPU=1"]}))
    assert "--resources GPU=1" in _script_of(_cluster(jobqueue={"cores": 1, "memory": "4GiB", "resources": {"GPU": 1}}))
    for directive in ("--gres=gpu:1", "--gres=gpu:a100:1", "--gpus=1", "--gpus-per-node=v100:1"):
        with pytest.raises(ConfigError, match="asks the batch system for 1 GPU.*gpus_per_job is 2"):
            _script_of(_cluster(jobqueue={"cores": 2, "memory": "4GiB", "gpus_per_job": 2,
                                          "job_extra_directives": [directive]}))
    with pytest.raises(ConfigError, match="asks the batch system for 1 GPU"):
        _script_of(_cluster(kind="pbs", jobqueue={"cores": 2, "memory": "4GiB", "gpus_per_job": 2,
                                                  "resource_spec": "select=1:ncpus=2:ngpus=1"}))
    assert [gpu_for_worker(f"j-{i}", "4,5,6", 3) for i in range(3)] == ["4", "5", "6"]
    assert [gpu_for_worker(f"j-{i}", None, 2) for i in range(2)] == ["0", "1"]     # no binding: the node's 0, 1
    with pytest.raises(GPUShortageError, match="2 workers but sees 1 GPU"):
        gpu_for_worker("j-1", "3", 2)
    with pytest.raises(GPUShortageError, match="not one of its job's 2 workers"):
        gpu_for_worker("j-2", "3,4", 2)
    with pytest.raises(GPUShortageError, match="not named <job>-<i>"):
        gpu_for_worker("tcp://worker", "3,4", 2)
    assert gpu_for_worker("j-0", "3", 1) is None                                  # one worker: nothing to split


def test_gpu_jobs_ask_for_their_gpus_and_each_worker_keeps_one(monkeypatch):
    pytest.importorskip("dask_jobqueue")
    from pipeline.worker_init import GPU_SPLIT_ENV, gpu_for_worker
    c = _cluster(threads_per_worker=4, jobqueue={"cores": 8, "processes": 2, "memory": "32GiB", "gpus_per_job": 2})
    lines = _script_of(c).splitlines()
    assert "#SBATCH --gres=gpu:2" in lines and f"export {GPU_SPLIT_ENV}=2" in lines, lines
    assert "--nworkers 2" in lines[-1] and "--nthreads 4" in lines[-1] and "--resources GPU=1" in lines[-1]
    own = _script_of(_cluster(jobqueue={"cores": 1, "memory": "4GiB", "gpus_per_job": 1,
                                        "job_extra_directives": ["--gpus=1"]})).splitlines()
    assert "#SBATCH --gpus=1" in own and not any("--gres" in ln for ln in own)     # the config's own request
    # a job of N workers names them <job>-0 .. <job>-(N-1): worker i keeps the job's GPU i
    assert [gpu_for_worker(f"SLURMCluster-3-{i}", "4,5") for i in range(3)] == ["4", "5", "4"]
    assert gpu_for_worker("SLURMCluster-3", "0") is None and gpu_for_worker("w-1", None) is None
    assert gpu_for_worker("name", "0,1") is None
    from types import SimpleNamespace

    from pipeline import worker_init
    monkeypatch.setenv(GPU_SPLIT_ENV, "2")
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "4,5")
    worker_init.dask_setup(SimpleNamespace(name="SLURMCluster-3-1"))        # the preload hook, before CUDA
    assert os.environ["CUDA_VISIBLE_DEVICES"] == "5"


@pytest.mark.parametrize("tpw, jobqueue, message", [
    (1, {"cores": 4, "processes": 3}, "cores (4) must equal processes (3) x dataset.cluster.threads_per_worker (1)"),
    (2, {"cores": 4, "processes": 4}, "set processes: 2 or dataset.cluster.threads_per_worker: 1"),
    (2, {"cores": 3}, "jobqueue.cores (3) must be a multiple of dataset.cluster.threads_per_worker (2)"),
    (1, {"cores": 2, "processes": 0}, "jobqueue.processes must be an integer >= 1"),
    (1, {"cores": 0}, "jobqueue.cores must be an integer >= 1"),
    (1, {"cores": 4, "job_cpu": 2}, "jobqueue.job_cpu must be null (= cores) or an integer >= cores (4)"),
    (1, {"cores": 1, "memory": "lots"}, "jobqueue.memory must be a size like '4GiB'"),
    (1, {"cores": 1, "resources": {"GPU": 0}}, "jobqueue.resources must be a mapping of resource names"),
    (1, {"cores": 1, "resources": ["GPU"]}, "jobqueue.resources must be a mapping of resource names"),
    (1, {"cores": 1, "resources": {"GPU": 1}, "worker_extra_args": ["--resources", "GPU=1"]},
     "worker resources are given twice"),
    (1, {"cores": 1, "job_script_prologue": {"a": 1}}, "jobqueue.job_script_prologue must be a list of shell lines"),
    (1, {"cores": 2, "gpus_per_job": 1}, "jobqueue.gpus_per_job must be an integer >= 1 equal to the job's workers"),
    (1, {"cores": 1, "gpus_per_job": 0}, "jobqueue.gpus_per_job must be an integer >= 1"),
])
def test_bad_job_settings_are_config_errors(tpw, jobqueue, message):
    pytest.importorskip("dask_jobqueue")
    from pipeline.jobs import jobqueue_cluster
    from pipeline.errors import ConfigError
    jq = {"memory": "1GiB", **jobqueue}
    with pytest.raises(ConfigError) as e:
        jobqueue_cluster(_cluster(threads_per_worker=tpw, jobqueue=jq))
    assert message in str(e.value) and "\n" not in str(e.value), str(e.value)


def test_a_bad_job_setting_stops_the_command_with_exit_2(tmp_path, capsys):
    pytest.importorskip("dask_jobqueue")
    from pipeline.__main__ import main
    d = yaml.safe_load(SMOKE_SLURM.read_text())
    d["cluster"]["jobqueue"]["processes"] = 2                   # 1 core, 2 single-threaded workers
    cfg = tmp_path / "bad.yaml"
    cfg.write_text(yaml.safe_dump(d))
    rc = main(["dataset", "--config", str(cfg), "--out", str(tmp_path / "s.zarr"), "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2 and "cores (1) must equal processes (2) x dataset.cluster.threads_per_worker (1)" in err, err
    assert len(err.strip().splitlines()) == 1


def test_job_python_is_taken_from_the_checkout():
    from pipeline.jobs import job_python
    assert job_python(".venv/bin/python") == f"{ROOT}/.venv/bin/python"
    assert job_python("/opt/py/bin/python") == "/opt/py/bin/python"
    assert job_python("python3") == "python3"                    # the node's PATH
    assert job_python("$HOME/venv/bin/python") == "$HOME/venv/bin/python"     # the job's shell expands it


def test_local_slurm_script_is_sound_and_names_what_is_missing():
    assert subprocess.run(["bash", "-n", str(SCRIPT)]).returncode == 0
    r = subprocess.run(["bash", str(SCRIPT)], capture_output=True, text=True)
    assert r.returncode == 2 and "usage:" in r.stderr and "up|down|status" in r.stderr
    runuser = shutil.which("runuser")
    if os.geteuid() != 0 or runuser is None:
        return
    # as another user, without /usr/sbin on PATH: the daemons are "missing", and nothing is installed
    r = subprocess.run([runuser, "-u", "nobody", "--", "env", "PATH=/usr/bin:/bin", "LOCAL_SLURM_DIR=/nonexistent/x",
                        "bash", str(SCRIPT), "up"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 1, r.stdout + r.stderr
    assert "missing command(s): munged slurmctld slurmd" in r.stderr or "must run as root" in r.stderr, r.stderr
    assert "apt-get install slurm-wlm munge" in r.stderr or "must run as root" in r.stderr
    assert not Path("/nonexistent/x").exists()


# ---- a real SLURM cluster ----------------------------------------------------------------------------
SHARED = Path(tempfile.gettempdir()) / "denoise-tests-local-slurm"     # .lock, .users (pids), .started


@contextmanager
def _shared_lock():
    with open(f"{SHARED}.lock", "a+") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        yield


def _users() -> set[int]:
    try:
        pids = {int(x) for x in Path(f"{SHARED}.users").read_text().split()}
    except (OSError, ValueError):
        return set()
    return {p for p in pids if Path(f"/proc/{p}").exists()}      # test processes that died drop out


def _set_users(pids: set[int]) -> None:
    Path(f"{SHARED}.users").write_text(" ".join(map(str, sorted(pids))))


def _local_slurm(*args, timeout=900) -> subprocess.CompletedProcess:
    return subprocess.run(["bash", str(SCRIPT), *args], capture_output=True, text=True, timeout=timeout)


@pytest.fixture(scope="session")
def slurm():
    """A running SLURM cluster: the one up already, else ``local-slurm.sh up`` (skips with its reason when
    that fails). Stopped at the end of the session by the last test process using it, if a test started it."""
    if os.geteuid() != 0:
        pytest.skip("SLURM tests need root: scripts/local-slurm.sh starts slurmd and munged (and installs them)")
    with _shared_lock():
        if _local_slurm("status", timeout=60).returncode != 0:
            r = _local_slurm("up")
            if r.returncode != 0:
                said = " | ".join((r.stderr + r.stdout).strip().splitlines()[-3:])
                pytest.skip(f"scripts/local-slurm.sh up failed: {said}")
            Path(f"{SHARED}.started").write_text(r.stdout)
        _set_users(_users() | {os.getpid()})
    yield
    with _shared_lock():
        users = _users() - {os.getpid()}
        _set_users(users)
        if not users and Path(f"{SHARED}.started").exists():
            _local_slurm("down", timeout=120)
            Path(f"{SHARED}.started").unlink()


def _queue(name: str) -> list[tuple[str, str]]:
    """(job id, state) of the jobs named ``name``."""
    out = subprocess.run(["squeue", "-h", "-n", name, "-o", "%i %T"], capture_output=True, text=True).stdout
    return [tuple(ln.split()) for ln in out.splitlines() if ln.strip()]


@pytest.fixture()
def slurm_config(slurm, tmp_path):
    """configs/smoke-slurm.yaml with a job name of this test's own and its job logs under ``tmp_path``;
    the test's jobs are cancelled at its end, whatever happened."""
    name = f"denoise-test-{uuid.uuid4().hex[:8]}"
    d = yaml.safe_load(SMOKE_SLURM.read_text())
    d["cluster"]["jobqueue"].update(job_name=name, log_directory=str(tmp_path / "slurm-logs"))
    path = tmp_path / "smoke-slurm.yaml"
    path.write_text(yaml.safe_dump(d, sort_keys=False))
    yield path, name
    subprocess.run(["scancel", "-n", name], capture_output=True)


def _cli(config: Path, out: Path, summary: Path | None = None, hook: str = "") -> list[str]:
    return [*python_m("pipeline", hook), "dataset", "--config", str(config), "--out", str(out), "--no-progress",
            *(["--summary-json", str(summary)] if summary else [])]


def _complete(store: Path) -> np.ndarray:
    import zarr
    try:
        return zarr.open_group(str(store), mode="r")["status/complete"][:]
    except Exception:  # noqa: BLE001 - not created yet
        return np.zeros(0, bool)


def _printed(lines: list[str], proc: subprocess.Popen, pattern: str, timeout: float = 120) -> str:
    """The first of ``lines`` (what a reader thread has collected of ``proc``'s output) matching ``pattern``."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout and proc.poll() is None:
        hit = next((ln for ln in list(lines) if re.search(pattern, ln)), None)
        if hit:
            return hit
        time.sleep(0.2)
    raise TimeoutError(f"no line matching {pattern!r} after {time.monotonic() - t0:.0f} s:\n{''.join(lines)[-3000:]}")


def _joined(logs: Path, name: str, n: int, timeout: float = 120) -> list[str]:
    """The ids of ``n`` jobs named ``name`` whose workers have registered with the scheduler (their job
    logs say so)."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        jobs = [j for j, _ in _queue(name)]
        joined = [j for j in jobs if (logs / f"{name}-{j}.err").exists()
                  and "Registered to" in (logs / f"{name}-{j}.err").read_text(errors="replace")]
        if len(joined) >= n:
            return joined
        time.sleep(0.2)
    raise TimeoutError(f"no {n} worker(s) of jobs {name} joined after {timeout} s: {_queue(name)}")


def _arrays(store: Path) -> dict[str, np.ndarray]:
    import zarr
    g = zarr.open_group(str(store), mode="r")
    return {path: arr[...] for path, arr in g.arrays()} | {
        f"{grp}/{name}": a[...] for grp, sub in g.groups() for name, a in sub.arrays()}


def _assert_same_store(a_path: Path, b_path: Path) -> None:
    """Every array equal (NaN where NaN), but the timing; the same dataset config in the root attributes."""
    import zarr
    a, b = _arrays(a_path), _arrays(b_path)
    assert a.keys() == b.keys() and "inputs/radiance" in a and "reference/radiance" in a
    for k in sorted(a):
        if k in TIMING:
            assert a[k].shape == b[k].shape
            continue
        assert a[k].dtype == b[k].dtype and a[k].shape == b[k].shape, k
        if a[k].dtype.kind == "f":
            np.testing.assert_array_equal(a[k], b[k], err_msg=k)         # NaN == NaN here, bit for bit otherwise
        else:
            assert (a[k] == b[k]).all(), k
    ga, gb = zarr.open_group(str(a_path), mode="r"), zarr.open_group(str(b_path), mode="r")
    assert ga.attrs["config"] == gb.attrs["config"]


@pytest.fixture(scope="module")
def local_store(slurm, tmp_path_factory):
    """configs/smoke.yaml on a LocalCluster: what every SLURM run must equal."""
    out = tmp_path_factory.mktemp("local") / "smoke.zarr"
    r = subprocess.run(_cli(SMOKE, out), env=_env(), cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    return out


def test_local_slurm_is_up_and_up_again_is_harmless(slurm):
    r = _local_slurm("up", timeout=120)
    assert r.returncode == 0 and "already running" in r.stdout, r.stdout + r.stderr
    m = re.search(r"up: node (\S+) \((\w+)\), (\d+) CPUs, (\d+) MB memory", r.stdout)
    # every CPU of the machine, whatever the affinity of the process that started it (a pinned test
    # process once wrote CPUs=1, and two jobs could not run side by side)
    assert m and int(m.group(3)) == os.cpu_count() and int(m.group(4)) > 0, r.stdout
    s = _local_slurm("status", timeout=60)
    assert s.returncode == 0 and "slurmctld: running" in s.stdout and "slurmd: running" in s.stdout, s.stdout
    assert re.search(rf"^{m.group(1)} (idle|mixed|allocated)", s.stdout, re.M), s.stdout


def test_smoke_slurm_renders_through_sbatch_jobs_and_equals_a_local_cluster_run(slurm_config, local_store, tmp_path):
    config, name = slurm_config
    out, summary = tmp_path / "slurm.zarr", tmp_path / "s.json"
    t0 = time.monotonic()
    r = subprocess.run(_cli(config, out, summary), env=_env(), cwd=ROOT, capture_output=True, text=True, timeout=600)
    took = time.monotonic() - t0
    assert r.returncode == 0, r.stdout[-4000:] + r.stderr[-4000:]
    s = json.loads(summary.read_text())
    assert s["cluster"] == "slurm" and s["complete"] == 4 and s["rendered"] == 4 and s["ok"] and s["validation"]["ok"]
    assert re.search(r"^cluster: slurm at tcp://127\.0\.0\.1:\d+, [12] worker\(s\)$", r.stdout, re.M), r.stdout
    assert re.search(r"^dashboard: http://127\.0\.0\.1:\d+/status$", r.stdout, re.M), r.stdout
    logs = sorted(p.name for p in (tmp_path / "slurm-logs").iterdir())
    assert any(n.startswith(f"{name}-") and n.endswith(".out") for n in logs), logs   # sbatch ran the jobs
    _assert_same_store(local_store, out)
    assert not _queue(name), "the run's jobs are cancelled when it ends"
    print(f"SLURM smoke run: {took:.1f} s wall, {s['elapsed_s']} s elapsed")


def test_workers_are_slurm_jobs_with_the_job_script_environment_and_the_dashboard_lists_them(slurm_config):
    from pipeline import cluster as cl
    from pipeline.config import load_config
    from core.variant import find_libllvm
    config, name = slurm_config
    conn = cl.connect(load_config(config).cluster)
    try:
        conn.client.wait_for_workers(2, timeout=120)
        env = conn.client.run(lambda: {k: os.environ.get(k) for k in
                                       ("SLURM_JOB_ID", "SLURM_JOB_NAME", "DRJIT_LIBLLVM_PATH", "OMP_NUM_THREADS")}
                              | {"cwd": os.getcwd()})
        jobs = {j for j, _ in _queue(name)}
        assert {e["SLURM_JOB_ID"] for e in env.values()} == jobs and len(jobs) == 2
        assert all(e["SLURM_JOB_NAME"] == name and e["OMP_NUM_THREADS"] == "1" and e["cwd"] == str(ROOT)
                   for e in env.values()), env
        if find_libllvm():
            assert {e["DRJIT_LIBLLVM_PATH"] for e in env.values()} == {find_libllvm()}
        page = urllib.request.urlopen(conn.dashboard.rsplit("/", 1)[0] + "/info/main/workers.html", timeout=30)
        body = page.read().decode()
        names = [w["name"] for w in conn.client.scheduler_info(n_workers=-1)["workers"].values()]
        assert len(names) == 2 and all(n in body for n in names), (names, body[:2000])
    finally:
        conn.close()


def test_a_job_slurm_can_never_run_is_refused_before_anything_is_submitted(slurm_config, tmp_path):
    config, name = slurm_config
    d = yaml.safe_load(config.read_text())
    d["cluster"]["jobqueue"].update(cores=4096, processes=4096)            # more CPUs than any node here
    config.write_text(yaml.safe_dump(d))
    t0 = time.monotonic()
    r = subprocess.run(_cli(config, tmp_path / "s.zarr"), env=_env(), cwd=ROOT, capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 2, r.stdout + r.stderr
    err = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(err) == 1 and err[0].startswith("error: SLURM would never run the worker job"), r.stderr
    assert "--cpus-per-task=4096" in err[0] and "sbatch --test-only says:" in err[0]
    assert time.monotonic() - t0 < 60 and not _queue(name)


def test_cancelled_jobs_are_replaced_and_no_frame_is_lost(slurm_config, local_store, tmp_path):
    """Every job of the run is ``scancel``ed mid-run: the run can only finish if new jobs are submitted
    (``pipeline.jobs.JobKeeper``); the frames the cancelled workers held are rendered by the new ones.

    Each job is stopped (SIGSTOP) the moment its worker has joined, so it holds the tasks the scheduler
    gave it and the run cannot end before the cancel (waiting for a frame instead raced: a 16-px frame
    takes under a second, and one worker once finished all four before the second job joined). The
    cancel waits until the run has seen both workers: its keeper replaces jobs whose workers it saw."""
    config, name = slurm_config
    out = tmp_path / "slurm.zarr"
    p = subprocess.Popen(_cli(config, out), env=_env(), cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                         text=True, start_new_session=True)
    lines: list[str] = []
    reader = threading.Thread(target=lambda: [lines.append(ln) for ln in p.stdout], daemon=True)
    reader.start()
    try:
        jobs: list[str] = []
        for n in (1, 2):                        # (a job cancelled before its worker joined is not the case here)
            new = [j for j in _joined(tmp_path / "slurm-logs", name, n) if j not in jobs]
            if new:
                subprocess.run(["scancel", "--signal=STOP", "--full", *new], check=True)
            jobs += new
        _printed(lines, p, r"^cluster: slurm at ")
        time.sleep(3 * KEEPER_EVERY)            # the keeper's checks see both workers
        done = _complete(out)
        assert len(jobs) == 2 and p.poll() is None and done.sum() < 4, "the run ended before its jobs could be cancelled"
        subprocess.run(["scancel", *jobs], check=True)
        p.wait(timeout=400)
        reader.join(timeout=30)
        log = "".join(lines)
    finally:
        if p.poll() is None:
            kill_group(p)
    assert p.returncode == 0, log[-4000:]
    for j in jobs:
        assert re.search(rf"^cluster: job {j} \(\S+\) ended \(cancelled, walltime reached or node lost\)",
                         log, re.M), log
    assert "frames:     4/4 complete (4 rendered now, 0 skipped, 0 failed)" in log and "validation: ok" in log
    _assert_same_store(local_store, out)


def test_jobs_that_end_right_after_joining_are_replaced(slurm_config, local_store, tmp_path):
    """Both jobs are cancelled the moment their workers have joined, long before the keeper's next look
    (its checks 20 s apart here): what the scheduler saw join counts, so the run neither says the jobs
    ended before a worker joined nor waits forever for jobs it never saw; it submits new ones and loses
    no frame."""
    config, name = slurm_config
    out = tmp_path / "slurm.zarr"
    p = subprocess.Popen(_cli(config, out, hook=setting("pipeline.jobs:JobKeeper.EVERY", 20.0)), env=_env(), cwd=ROOT,
                         stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)
    try:
        jobs: list[str] = []
        for n in (1, 2):
            new = [j for j in _joined(tmp_path / "slurm-logs", name, n) if j not in jobs]
            if new:
                subprocess.run(["scancel", "--signal=STOP", "--full", *new], check=True)   # it holds its tasks
            jobs += new
        subprocess.run(["scancel", *jobs], check=True)
        log, _ = p.communicate(timeout=400)
    finally:
        if p.poll() is None:
            kill_group(p)
    assert p.returncode == 0, log[-4000:]
    assert "ended before a worker joined" not in log
    for j in jobs:
        assert re.search(rf"^cluster: job {j} \(\S+\) ended", log, re.M), log
    assert "frames:     4/4 complete (4 rendered now, 0 skipped, 0 failed)" in log and "validation: ok" in log
    _assert_same_store(local_store, out)


@pytest.mark.slow
def test_a_job_that_reaches_its_walltime_loses_no_frame(slurm_config, local_store, tmp_path):
    """One job is stopped as its worker joins (SIGSTOP through ``scancel --signal``, so it still holds its
    frames' tasks when its limit comes, as a long render would) and its limit set to one minute (SLURM's
    smallest): SLURM ends it (TIMEOUT) a minute after it started, and its frames are rendered by the
    other job. Slow: the minute has to pass."""
    config, name = slurm_config
    out = tmp_path / "slurm.zarr"
    p = subprocess.Popen(_cli(config, out), env=_env(), cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                         text=True, start_new_session=True)
    try:
        job = _joined(tmp_path / "slurm-logs", name, 1)[0]   # stopped as it joins: it holds the tasks it
        subprocess.run(["scancel", "--signal=STOP", "--full", job], check=True)      # was given
        assert p.poll() is None and _complete(out).sum() < 4, "the run ended before a job could be stopped"
        subprocess.run(["scontrol", "update", f"JobId={job}", "TimeLimit=1"], check=True)
        log, _ = p.communicate(timeout=400)
    finally:
        if p.poll() is None:
            kill_group(p)
    assert p.returncode == 0, log[-4000:]
    state = subprocess.run(["scontrol", "show", "job", job], capture_output=True, text=True).stdout
    assert "JobState=TIMEOUT" in state and "TimeLimit=00:01:00" in state, state
    assert "frames:     4/4 complete (4 rendered now, 0 skipped, 0 failed)" in log and "validation: ok" in log
    _assert_same_store(local_store, out)


def test_a_killed_client_leaves_a_store_that_a_rerun_completes(slurm_config, local_store, tmp_path):
    """SIGKILL of the command (its scheduler dies with it) mid-run: its jobs' workers stop by themselves
    (``death_timeout``), and the same command again resumes to the store a LocalCluster makes. The kill
    lands right after the run's first commit (it pauses there: ``pause_at`` its commit seam); waiting for
    a frame instead raced, as 16-px frames can all finish between two looks at the store."""
    config, name = slurm_config
    out, flag = tmp_path / "slurm.zarr", tmp_path / "committed"
    p = subprocess.Popen(_cli(config, out, hook=pause_at("pipeline.dataset:_commit_hook", flag)), env=_env(),
                         cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        t0 = time.monotonic()
        while not flag.exists() and p.poll() is None and time.monotonic() - t0 < 300:
            time.sleep(0.2)
        running = p.poll() is None and flag.exists()
    finally:
        kill_group(p)
    before = _complete(out)
    assert running and 1 <= before.sum() < 4, "the run was not cut mid-run"
    orphans = {j for j, _ in _queue(name)}
    r = subprocess.run(_cli(config, out, tmp_path / "s.json"), env=_env(), cwd=ROOT, capture_output=True, text=True,
                       timeout=600)
    assert r.returncode == 0, r.stdout[-4000:] + r.stderr[-4000:]
    s = json.loads((tmp_path / "s.json").read_text())
    assert s["skipped"] == int(before.sum()) and s["complete"] == 4 and s["ok"]
    assert "lock: took over the lock of a dead run" in r.stdout
    assert f"resume: {int(before.sum())} frame(s) already complete" in r.stdout
    _assert_same_store(local_store, out)
    t0 = time.monotonic()              # the killed run's jobs end by themselves (no scheduler to serve)
    while orphans & {j for j, _ in _queue(name)} and time.monotonic() - t0 < 90:
        time.sleep(1)
    assert not orphans & {j for j, _ in _queue(name)}, _queue(name)


def test_jobs_whose_script_fails_are_a_clear_error_not_a_wait(slurm_config, tmp_path):
    config, name = slurm_config
    d = yaml.safe_load(config.read_text())
    d["cluster"]["jobqueue"]["python"] = "/nonexistent/bin/python"         # every job ends at once
    config.write_text(yaml.safe_dump(d))
    r = subprocess.run(_cli(config, tmp_path / "s.zarr"), env=_env(), cwd=ROOT, capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 2, r.stdout + r.stderr
    err = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(err) == 1 and "ended before a worker joined; the job script failed" in err[0], r.stderr
    assert str(tmp_path / "slurm-logs") in err[0] and not _queue(name)
