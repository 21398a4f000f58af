"""Every ``make bench`` suite runs (``python -m pipeline bench --only SUITE --tiny``), so a benchmark
cannot rot unseen (``make bench`` once failed on an import that ``pipeline.cluster`` no longer had).
Tiny sizes (``pipeline.bench.TINY``): the figures are meaningless, the code paths are the real ones.
About 60 s for the four suites on 2 cores."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from pipeline.bench import SUITES, TINY

ROOT = Path(__file__).resolve().parent.parent


def test_every_suite_has_a_tiny_size():
    assert set(TINY) == set(SUITES)


@pytest.mark.parametrize("suite", sorted(SUITES))
def test_bench_suite_runs_at_a_tiny_size(suite, tmp_path):
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    out = tmp_path / "bench.json"
    r = subprocess.run([sys.executable, "-m", "pipeline", "bench", "--only", suite, "--tiny", "--json", str(out)],
                       env=env, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    figures = json.loads(out.read_text())
    if suite == "scale":           # the contract: {stage: {"F": per-frame value}} at the top level
        from pipeline.bench_scale import STAGES
        assert set(STAGES) <= set(figures) and all(set(figures[st]) == {"6", "12"} for st in STAGES), figures
        assert figures["files"]["12"] < figures["files"]["6"] * 1.5 and "re-run on the complete store" in r.stdout
    else:
        assert list(figures) == [suite] and figures[suite], figures
    if suite == "render":          # the throughput measure: the dataset run against plain mi.render
        assert 0 < figures["render"]["dataset_vs_mi_render"] < 100, figures["render"]
        assert "vs plain mi.render of the same frames and samples" in r.stdout
    assert f"--- {suite} done in" in r.stdout
