"""The chaos run (``make chaos``): one dataset rendered through random faults, then a training run
through SIGKILLs; nothing may be lost and nothing but documented lines may be printed.

The dataset part renders ``--config`` (default ``configs/chaos.yaml``, 300 frames) on a LocalCluster
into an ``s3://`` store on a local S3 server (moto's server mode, started here), with the same command
a user runs (``python -m pipeline dataset --config C --out URL --no-progress``). At random moments
drawn from ``--seed`` it injects ``--faults`` faults, at least 3 of each kind (while the faults asked
for allow it; the kinds are shuffled):

- ``worker``: a Dask worker process SIGKILLed (the run goes on: Dask retries its task elsewhere);
- ``s3``: the S3 server stopped and started again with its data after a few seconds (the run rides it
  out on botocore's retries, or stops with exit 5 and is run again);
- ``sigint``: the main process group sent SIGINT, as a terminal's Ctrl-C does (exit 130), then resumed
  with the same command;
- ``sigkill``: the main process SIGKILLed, then resumed with the same command.

It goes on until the run completes. Then the store must equal a clean run's of the same config, array
by array (the timings in ``frames/render_seconds`` aside: they are wall clock), every exit code must be a
documented one, every line on stderr one of the documented one-line messages (:data:`DOCUMENTED`), and
no ``.partial`` object nor the run's lease may be left in the store.

The training part trains ``--train-model`` for ``--train-steps`` on the clean store, SIGKILLs it
``--train-kills`` times (at random steps, and, where the kill can be timed to it, while
``checkpoint.pt`` is being written: the temporary file beside it exists) and resumes it with the same
command each time; the final weights must be bit-equal to an uninterrupted run's, and no temporary
file may be left in the run folder.

Exit 0 when every check holds, 1 otherwise; the faults and figures go to ``OUT/chaos.json``.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import os
import random
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
KINDS = ("worker", "s3", "sigint", "sigkill")
BUCKET = "chaos"

# The exit codes the README's table documents (-9: the SIGKILL this script sends, not the program's).
EXITS = {0: "ok", 1: "problems found", 2: "bad input", 3: "damaged", 4: "disk full", 5: "S3 unreachable",
         130: "interrupted", -signal.SIGKILL: "killed here"}

# Every line a dataset run may print on stderr under these faults: the README's documented one-line messages.
DOCUMENTED = [
    r"interrupted(: complete frames stay in \S+; run the same command again to resume)?",   # Ctrl-C, exit 130
    r"error: .*could not be reached.*run the same command again.*",          # the S3 endpoint gone, exit 5
    r"warning: .*",                                                          # a notice of the run
    r"",
]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class S3Server:
    """moto's S3 server on 127.0.0.1, stopped and started again on the same port with the same data
    (moto keeps its data in this process)."""

    def __init__(self):
        from moto import server as moto_server
        import logging
        logging.getLogger("werkzeug").setLevel(logging.ERROR)
        self.moto = moto_server
        self.port = _free_port()
        self.endpoint = f"http://127.0.0.1:{self.port}"
        self.srv = None

    def start(self) -> None:
        self.srv = self.moto.ThreadedMotoServer(ip_address="127.0.0.1", port=self.port, verbose=False)
        self.srv.start()

    def stop(self) -> None:
        if self.srv is not None:
            self.srv.stop()
            self.srv = None


def _env(extra: dict | None = None) -> dict:
    env = {**os.environ, "PYTHONUNBUFFERED": "1", **(extra or {})}
    env.setdefault("DENOISE_DATA", str(ROOT / "data"))
    return env


def _schedule(rng: random.Random, n: int) -> list[str]:
    """``n`` fault kinds, at least 3 of each where ``n`` allows, shuffled."""
    each = min(3, n // len(KINDS))
    kinds = [k for k in KINDS for _ in range(each)]
    kinds += [rng.choice(KINDS) for _ in range(n - len(kinds))]
    rng.shuffle(kinds)
    return kinds


def _worker_pids(pid: int) -> list[int]:
    """The Dask worker processes under ``pid`` (multiprocessing's spawned children, its resource tracker
    aside)."""
    import psutil
    try:
        kids = psutil.Process(pid).children(recursive=True)
    except psutil.NoSuchProcess:
        return []
    out = []
    for p in kids:
        try:
            cmd = " ".join(p.cmdline())
        except psutil.Error:
            continue
        if "spawn_main" in cmd:
            out.append(p.pid)
    return out


def _kill_group(proc: subprocess.Popen) -> None:
    """SIGKILL what is left of ``proc``'s process group (a killed main process's workers die with it, or here)."""
    with contextlib.suppress(ProcessLookupError):
        os.killpg(proc.pid, signal.SIGKILL)
    proc.wait(timeout=60)


def _undocumented(stderr: str) -> list[str]:
    pats = [re.compile(p) for p in DOCUMENTED]
    return [ln for ln in stderr.splitlines() if not any(p.fullmatch(ln.strip()) for p in pats)]


def _s3_keys(url: str) -> list[str]:
    import boto3
    bucket, _, prefix = url.split("://", 1)[1].partition("/")
    pages = boto3.client("s3").get_paginator("list_objects_v2").paginate(Bucket=bucket, Prefix=prefix)
    return [o["Key"] for page in pages for o in page.get("Contents", [])]


def _arrays(store: str) -> dict:
    import zarr
    g = zarr.open_group(store, mode="r")
    return {f"{grp}/{name}": a[...] for grp, sub in g.groups() for name, a in sub.arrays()}


def _compare(a_url: str, b_url: str) -> list[str]:
    """The arrays that differ between two stores (wall-clock timings aside)."""
    import numpy as np
    a, b = _arrays(a_url), _arrays(b_url)
    out = [f"{k}: only in one store" for k in sorted(set(a) ^ set(b))]
    for k in sorted(set(a) & set(b)):
        if k == "frames/render_seconds":
            continue
        x, y = a[k], b[k]
        if x.shape != y.shape or x.dtype != y.dtype or not np.array_equal(x, y, equal_nan=x.dtype.kind in "fc"):
            out.append(f"{k}: differs")
    return out


def _dataset_cmd(config: str, out: str) -> list[str]:
    return [sys.executable, "-m", "pipeline", "dataset", "--config", config, "--out", out, "--no-progress"]


class Run:
    """One dataset command, its output read as it comes (so the pipes never fill)."""

    def __init__(self, cmd: list[str], env: dict):
        import threading
        self.proc = subprocess.Popen(cmd, env=env, cwd=ROOT, text=True, stdout=subprocess.PIPE,
                                     stderr=subprocess.PIPE, start_new_session=True)
        self.out: list[str] = []
        self.err: list[str] = []
        self.threads = [threading.Thread(target=self._pump, args=(s, buf), daemon=True)
                        for s, buf in ((self.proc.stdout, self.out), (self.proc.stderr, self.err))]
        for t in self.threads:
            t.start()

    @staticmethod
    def _pump(stream, buf: list) -> None:
        for line in stream:
            buf.append(line)

    def alive_after(self, seconds: float) -> bool:
        try:
            self.proc.wait(timeout=seconds)
            return False
        except subprocess.TimeoutExpired:
            return True

    def finish(self, timeout: float) -> int | None:
        """The exit code, or None when the run hung past ``timeout`` (then it is killed)."""
        try:
            self.proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            _kill_group(self.proc)
            return None
        if self.proc.returncode == -signal.SIGKILL:
            time.sleep(1.0)
            _kill_group(self.proc)        # what the killed main process left
        for t in self.threads:
            t.join(timeout=10)
        return self.proc.returncode


def _inject(kind: str, run: Run, rng: random.Random, server: "S3Server") -> dict | None:
    """One fault into a live run; None when it cannot land now (no worker process yet)."""
    fault: dict = {"kind": kind}
    if kind == "worker":
        pids = _worker_pids(run.proc.pid)
        if not pids:
            return None
        fault["pid"] = rng.choice(sorted(pids))
        os.kill(fault["pid"], signal.SIGKILL)
    elif kind == "s3":
        server.stop()
        fault["down_s"] = round(rng.uniform(1.0, 8.0), 2)
        time.sleep(fault["down_s"])
        server.start()
    elif kind == "sigint":
        os.killpg(run.proc.pid, signal.SIGINT)      # a terminal's Ctrl-C: the whole foreground group
    else:
        os.kill(run.proc.pid, signal.SIGKILL)
    return fault


def _clean_run(args, report: dict) -> str | None:
    """Render the config into a local store with no fault (resumed if made before); the clean run's
    seconds space the faults. Returns the failure, or None."""
    clean = str(Path(args.out) / "clean.zarr")
    before = Path(args.out) / "chaos.json"
    if args.fresh:
        shutil.rmtree(clean, ignore_errors=True)
    made = (Path(clean) / "zarr.json").exists()
    print(f"chaos: a clean run of {args.config} into {clean}", flush=True)
    t0 = time.monotonic()
    r = subprocess.run(_dataset_cmd(args.config, clean), env=_env(), cwd=ROOT, capture_output=True, text=True)
    if r.returncode != 0:
        return f"the clean run failed (exit {r.returncode}): {r.stderr.strip()[-500:]}"
    report["clean_s"] = round(time.monotonic() - t0, 1)
    if made and before.exists():                 # a store made before: its first run's time spaces the faults
        report["clean_s"] = json.loads(before.read_text()).get("clean_s", report["clean_s"])
    return None


def _faulted_runs(args, rng: random.Random, url: str, env: dict, server: S3Server, gap: float) -> tuple:
    """Run the dataset command again and again, each time with the faults still due at random moments,
    until a run exits 0. Returns (runs, faults, failures)."""
    kinds = _schedule(rng, args.faults)
    runs: list[dict] = []
    faults: list[dict] = []
    while len(runs) <= 4 * args.faults + 10:
        run = Run(_dataset_cmd(args.config, url), env)
        while len(faults) < len(kinds):
            delay = rng.uniform(0.5, 1.5) * gap
            if not run.alive_after(delay):
                break
            fault = _inject(kinds[len(faults)], run, rng, server)
            if fault is None:
                continue
            faults.append({**fault, "run": len(runs), "after_s": round(delay, 2)})
            print(f"chaos: fault {len(faults)}/{len(kinds)}: {faults[-1]}", flush=True)
            if fault["kind"] in ("sigint", "sigkill"):
                break
        rc = run.finish(args.timeout)
        err = "".join(run.err)
        runs.append({"i": len(runs), "rc": rc, "undocumented": _undocumented(err),
                     "last_line": (err.strip().splitlines() or [""])[-1][:300]})
        print(f"chaos: run {len(runs) - 1} exit {rc} ({EXITS.get(rc, 'undocumented')})"
              + (f": {runs[-1]['last_line']}" if runs[-1]["last_line"] else ""), flush=True)
        if rc is None:
            return runs, faults, [f"run {len(runs) - 1} hung for {args.timeout} s"]
        if rc == 0:
            return runs, faults, []
    return runs, faults, [f"no complete run after {len(runs)} tries"]


def _checks(args, runs: list[dict], faults: list[dict], url: str, clean: str, report: dict) -> list[str]:
    """What must hold once the faulted run completed (module docstring)."""
    failed = []
    if len(faults) < args.faults:
        failed.append(f"only {len(faults)} of {args.faults} faults were injected before the run completed")
    for r in runs:
        if r["rc"] is not None and r["rc"] not in EXITS:
            failed.append(f"run {r['i']}: exit {r['rc']} is not a documented exit code")
        failed += [f"run {r['i']} (exit {r['rc']}): undocumented stderr line: {ln[:300]}" for ln in r["undocumented"]]
    if runs and runs[-1]["rc"] == 0:
        diff = _compare(url, clean)
        failed += [f"store differs from the clean run: {d}" for d in diff]
        report["arrays_differing"] = len(diff)
        left = [k for k in _s3_keys(url) if k.endswith(".partial") or k.endswith("dataset.lock")]
        failed += [f"left in the store: {k}" for k in left]
    return failed


def dataset_chaos(args, rng: random.Random, report: dict) -> list[str]:
    """The dataset part (module docstring); returns the failed checks."""
    bad = _clean_run(args, report)
    if bad:
        return [bad]
    # a fault every 0.4 / faults of the clean run's time on average: the faults the main process takes cost
    # restarts, and every fault must land before the run completes
    gap = args.gap or max(2.0, 0.4 * report["clean_s"] / max(1, args.faults))
    server = S3Server()
    server.start()
    aws = {"AWS_ENDPOINT_URL": server.endpoint, "AWS_ACCESS_KEY_ID": "chaos", "AWS_SECRET_ACCESS_KEY": "chaos",
           "AWS_DEFAULT_REGION": "us-east-1"}
    os.environ.update(aws)
    import boto3
    boto3.client("s3").create_bucket(Bucket=BUCKET)
    url = f"s3://{BUCKET}/chaos.zarr"
    t0 = time.monotonic()
    try:
        runs, faults, failed = _faulted_runs(args, rng, url, _env(aws), server, gap)
        report["chaos_s"] = round(time.monotonic() - t0, 1)
        report["faults"], report["runs"] = faults, runs
        report["fault_counts"] = {k: sum(f["kind"] == k for f in faults) for k in KINDS}
        return failed + _checks(args, runs, faults, url, str(Path(args.out) / "clean.zarr"), report)
    finally:
        server.stop()


def training_chaos(args, rng: random.Random, report: dict) -> list[str]:
    """The training part (module docstring); returns the failed checks."""
    failed: list[str] = []
    store = str(Path(args.out) / "clean.zarr")
    base = [sys.executable, "-m", "training", "train", "--model", args.train_model, "--store", store,
            "--steps", str(args.train_steps), "--checkpoint-every", str(args.checkpoint_every), "--seed",
            str(args.seed), "--workers", "0", "--no-progress"]
    ref, run = Path(args.out) / "train-clean", Path(args.out) / "train-chaos"
    for d in (ref, run):
        shutil.rmtree(d, ignore_errors=True)
    r = subprocess.run(base + ["--out", str(ref)], env=_env(), cwd=ROOT, capture_output=True, text=True)
    if r.returncode != 0:
        return [f"the uninterrupted training run failed (exit {r.returncode}): {r.stderr.strip()[-500:]}"]
    kills = []
    while True:
        proc = subprocess.Popen(base + ["--out", str(run)], env=_env(), cwd=ROOT, text=True,
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True)
        if len(kills) < args.train_kills:
            inside = rng.random() < 0.5
            deadline = time.monotonic() + rng.uniform(1.0, 6.0)
            hit = None
            while proc.poll() is None:
                tmp = list(run.glob(".checkpoint.pt-*.tmp")) if run.exists() else []
                late = time.monotonic() >= deadline + (15.0 if inside else 0.0)
                if (inside and tmp) or late:        # a write caught in the act, or the moment has come
                    os.kill(proc.pid, signal.SIGKILL)
                    hit = "inside a checkpoint write" if tmp else "between checkpoints"
                    break
                time.sleep(0.0002 if inside else 0.05)
            if hit:
                proc.wait()
                _kill_group(proc)
                kills.append(hit)
                print(f"chaos: training kill {len(kills)}/{args.train_kills}: {hit}", flush=True)
                continue
        err = proc.communicate(timeout=args.timeout)[1]
        if proc.returncode != 0:
            failed.append(f"the resumed training run exited {proc.returncode}: {err.strip()[-500:]}")
        break
    report["training_kills"] = kills
    if len(kills) < args.train_kills:
        failed.append(f"only {len(kills)} of {args.train_kills} training kills landed before the run ended")
    if (run / "checkpoint.pt").exists():
        import torch
        a = torch.load(ref / "checkpoint.pt", weights_only=True)["state_dict"]
        b = torch.load(run / "checkpoint.pt", weights_only=True)["state_dict"]
        differ = [k for k in a if not torch.equal(a[k], b[k])]
        failed += [f"training weights differ from the uninterrupted run's: {k}" for k in differ]
        left = [p.name for p in run.iterdir() if p.name.endswith(".tmp")]
        failed += [f"left in the run folder: {n}" for n in left]
    return failed


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="scripts/chaos.py", description=__doc__.split("\n\n")[0])
    p.add_argument("--config", default=str(ROOT / "configs" / "chaos.yaml"))
    p.add_argument("--out", default=str(ROOT / "data" / "chaos"), help="where the clean store, runs and report go")
    p.add_argument("--seed", type=int, default=0, help="draws the faults, their moments and the training kills")
    p.add_argument("--faults", type=int, default=20)
    p.add_argument("--train-kills", type=int, default=5)
    p.add_argument("--train-model", default="unet", help="a model whose checkpoint takes long enough to write "
                   "that a kill can land inside the write (unet: about 12 MB with its optimiser state)")
    p.add_argument("--train-steps", type=int, default=300)
    p.add_argument("--checkpoint-every", type=int, default=10)
    p.add_argument("--timeout", type=float, default=1800.0, help="seconds a run may take before it counts as hung")
    p.add_argument("--gap", type=float, default=0.0, help="mean seconds between faults (0: the clean run's time "
                   "times 0.4 spread over the faults)")
    p.add_argument("--fresh", action="store_true", help="render the clean store again")
    p.add_argument("--skip-training", action="store_true")
    p.add_argument("--skip-dataset", action="store_true", help="only the training part (on the clean store made "
                   "before)")
    args = p.parse_args(argv)
    Path(args.out).mkdir(parents=True, exist_ok=True)
    rng = random.Random(args.seed)
    report = {"seed": args.seed, "config": args.config, "faults_asked": args.faults}
    t0 = time.monotonic()
    failed = [] if args.skip_dataset else dataset_chaos(args, rng, report)
    if not args.skip_training and not failed:
        failed += training_chaos(args, rng, report)
    report["seconds"] = round(time.monotonic() - t0, 1)
    report["failed"] = failed
    (Path(args.out) / "chaos.json").write_text(json.dumps(report, indent=1))
    counts = report.get("fault_counts", {})
    print(f"chaos: {sum(counts.values())} faults ({', '.join(f'{k} {v}' for k, v in counts.items())}), "
          f"{len(report.get('runs', []))} dataset runs, {len(report.get('training_kills', []))} training kills, "
          f"{report['seconds']} s")
    for f in failed:
        print(f"chaos: FAILED: {f}", file=sys.stderr)
    print("chaos: " + ("FAILED" if failed else "passed: the store equals the clean run's, every exit and stderr "
                       "line documented, nothing left behind; training bit-equal through its kills"))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
