"""The chaos run (``scripts/chaos.py``, ``make chaos``) at a small size: a 6-frame dataset on one worker rendered into an
``s3://`` store through one fault of each kind (a worker SIGKILLed, the S3 server stopped and started
again, the main process Ctrl-C'd and SIGKILLed), then a training run SIGKILLed once; the store must equal
a clean run's, every exit code and stderr line be documented, nothing be left behind, and the weights be
bit-equal to an uninterrupted run's. And the two faults it found, each alone."""
from __future__ import annotations

import json
import multiprocessing
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

pytest.importorskip("moto.server", reason="the chaos run needs moto's server (pip install -e .[dev])")

ROOT = Path(__file__).resolve().parent.parent


def _small_config(tmp_path: Path) -> Path:
    cfg = yaml.safe_load((ROOT / "configs" / "chaos.yaml").read_text())
    cfg["scenes"] = [{"kind": "indoor", "count": 2}, {"kind": "outdoor", "count": 2},
                     {"kind": "outdoor", "count": 1, "frames": 2}]
    cfg["cluster"]["workers"] = 1          # the suite runs beside it on the same cores
    path = tmp_path / "chaos-small.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


@pytest.mark.xdist_group("chaos")
def test_a_small_chaos_run_loses_nothing_and_prints_only_documented_lines(tmp_path):
    out = tmp_path / "chaos"
    r = subprocess.run([sys.executable, str(ROOT / "scripts" / "chaos.py"), "--config", str(_small_config(tmp_path)),
                        "--out", str(out), "--seed", "0", "--faults", "4", "--gap", "3", "--train-kills", "1",
                        "--train-steps", "60", "--timeout", "600"], cwd=ROOT, capture_output=True, text=True,
                       timeout=1200)
    report = json.loads((out / "chaos.json").read_text())
    assert r.returncode == 0 and report["failed"] == [], r.stdout[-3000:] + r.stderr[-3000:]
    assert report["fault_counts"] == {"worker": 1, "s3": 1, "sigint": 1, "sigkill": 1}, report["fault_counts"]
    assert len(report["training_kills"]) == 1 and report["arrays_differing"] == 0
    assert report["runs"][-1]["rc"] == 0 and all(run["undocumented"] == [] for run in report["runs"])


def test_a_checkpoint_write_cut_short_leaves_nothing_after_the_resume(tmp_path):
    """A SIGKILL inside ``torch.save`` leaves ``write_atomically``'s temporary file (its ``finally`` never
    runs); the run that resumes in that folder deletes it."""
    from test_training import make_store
    store = make_store(tmp_path / "tiny.zarr")
    run = tmp_path / "run"
    run.mkdir()
    (run / ".checkpoint.pt-k1ll3d.tmp").write_bytes(b"half a checkpoint")
    r = subprocess.run([sys.executable, "-m", "training", "train", "--model", "nbg", "--store", store,
                        "--out", str(run), "--steps", "2", "--crop", "16", "--workers", "0", "--no-progress"],
                       cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert sorted(p.name for p in run.iterdir()) == ["checkpoint.pt", "metrics.csv"]


def _sigint_disposition(q) -> None:
    q.put(signal.getsignal(signal.SIGINT) == signal.SIG_IGN)


def test_a_local_clusters_processes_ignore_ctrl_c_from_their_first_instruction():
    """The worker processes a LocalCluster spawns took a terminal's Ctrl-C while still importing Dask
    (before their preload could ignore it) and printed a KeyboardInterrupt traceback: they now start with
    SIGINT ignored. Without the wrapper, a spawned child's SIGINT handler is Python's own."""
    from pipeline import worker_init
    ctx = multiprocessing.get_context("spawn")
    saved = list(sys.warnoptions)
    try:
        worker_init.spawn_ignoring_interrupts()
        q = ctx.Queue()
        p = ctx.Process(target=_sigint_disposition, args=(q,))
        p.start()
        ignored = q.get(timeout=120)
        p.join(timeout=60)
    finally:
        ctx.set_executable(sys.executable)
        sys.warnoptions[:] = saved
    assert ignored is True
