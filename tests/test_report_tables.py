"""What the report shows: every mean of its tables with its 95% interval, a kind whose frames repeat
another's named once rather than as a second column, the intervals as error bars on the speed-against-
error plot, and its JSON files readable as its other outputs are."""
from __future__ import annotations

import os
import stat

import numpy as np
import pytest

from training import report
from training.evaluate import summarize


def _frames(rng, shift=0.0):
    """Eight still frames: four indoor with defocus and motion (as the default store's indoor scenes), four
    outdoor with neither."""
    out = []
    for i in range(8):
        indoor = i < 4
        out.append({"index": i, "clip": i, "scene_kind": "indoor" if indoor else "outdoor", "has_defocus": indoor,
                    "has_motion": indoor, "has_fireflies": False, "relmse": float(rng.uniform(0.1, 0.2) + shift),
                    "psnr": float(rng.uniform(20, 25)), "smape": 0.1, "ssim": 0.9, "flip": 0.1})
    return out


def _result(label, frames, speed=None):
    return {"label": label, "frames": frames, **summarize(frames, []), "speed": speed and {"ms_per_mp": speed},
            "params": 0}


def test_tables_give_every_mean_its_interval_and_name_repeated_kinds_once():
    rng = np.random.default_rng(0)
    results = [_result("input", _frames(rng)), _result("nbg", _frames(rng, -0.05), speed=700.0)]
    by_kind = results[0]["by_kind"]
    assert by_kind["defocus"]["same_as"] == "indoor" and by_kind["motion"]["same_as"] == "indoor"
    assert by_kind["outdoor"]["same_as"] is None and by_kind["plain"]["same_as"] == "outdoor"
    lo, hi = by_kind["indoor"]["ci95"]["relmse"]
    assert lo < by_kind["indoor"]["relmse"] < hi
    main = report.table_markdown(results)
    row = next(ln for ln in main.splitlines() if ln.startswith("| nbg |"))
    m, ci = results[1]["mean"]["relmse"], results[1]["ci95"]["relmse"]
    assert f"{m:.4f} [{ci[0]:.4f}, {ci[1]:.4f}]" in row
    kinds = report.kinds_markdown(results)
    head = kinds.splitlines()[0]
    assert "indoor (4; also defocus, motion)" in head and "outdoor (4; also plain)" in head
    assert "| defocus" not in head and "| motion" not in head
    i_lo, i_hi = results[1]["by_kind"]["indoor"]["ci95"]["relmse"]
    assert f"[{i_lo:.4f}, {i_hi:.4f}]" in kinds.splitlines()[3]
    by = report.comparisons_by_kind(results, "input")
    assert [k for k, _ in by["kinds"]] == ["indoor", "outdoor"]


def test_the_plot_draws_each_interval(tmp_path, monkeypatch):
    from matplotlib.figure import Figure
    rng = np.random.default_rng(1)
    results = [_result("input", _frames(rng)), _result("nbg", _frames(rng, -0.05), speed=700.0)]
    drawn = {}

    def keep(fig_self, path, *a, **k):
        ax = fig_self.axes[0]
        drawn["bars"] = [c for c in ax.containers if type(c).__name__ == "ErrorbarContainer"]
        drawn["bands"] = [p for p in ax.patches]
    monkeypatch.setattr(Figure, "savefig", keep)
    report.plot_speed_vs_error(results, tmp_path / "p.png")
    assert len(drawn["bars"]) == 1 and len(drawn["bands"]) == 1
    seg = drawn["bars"][0].lines[2][0].get_segments()[0]
    np.testing.assert_allclose(sorted(seg[:, 1]), results[1]["ci95"]["relmse"], rtol=1e-9)


def test_json_and_checkpoints_get_the_permissions_of_any_new_file(tmp_path):
    import torch

    from training.jsonio import write
    old = os.umask(0o022)
    try:
        write(tmp_path / "e.json", {"a": 1})
        (tmp_path / "plain.txt").write_text("x")
        from training.checkpoint import _write
        _write(tmp_path / "c.pt", {"w": torch.zeros(1)})
    finally:
        os.umask(old)
    modes = {p.name: stat.S_IMODE(p.stat().st_mode) for p in tmp_path.iterdir()}
    assert modes == {"e.json": 0o644, "plain.txt": 0o644, "c.pt": 0o644}, {k: oct(v) for k, v in modes.items()}


def test_each_method_is_paired_with_its_own_input_and_worse_says_worse():
    """By default a method is compared with the noisy input at its own spp and input kind, never with a
    lower-spp input that flatters it: a layer model between the 1-spp and the 8-spp input reads "worse"
    against its own (8 spp), and the 1-spp model "better" against its own (1 spp)."""
    rng = np.random.default_rng(2)
    base = _frames(rng)

    def shifted(d):
        return [{**f, "relmse": f["relmse"] + d, "psnr": f["psnr"] - 40 * d} for f in base]

    def res(label, method, spp, kind, frames):
        return {**_result(label, frames), "method": method, "spp": spp, "input_kind": kind}
    results = [res("input @1spp", "input", 1, "pixels", shifted(0.2)), res("input @8spp", "input", 8, "pixels", base),
               res("layer", "layer", 8, "samples", shifted(0.05)), res("nbg", "nbg", 1, "pixels", shifted(0.1))]
    comp = report.comparisons(results)
    rows = {r["label"]: r for r in comp["rows"]}
    assert comp["baseline"] == report.OWN_INPUT and rows["layer"]["against"] == "input @8spp"
    assert rows["nbg"]["against"] == "input @1spp" and "input @1spp" not in rows and "input @8spp" not in rows
    table = report.comparisons_markdown(comp)
    layer = next(ln for ln in table.splitlines() if ln.startswith("| layer |"))
    nbg = next(ln for ln in table.splitlines() if ln.startswith("| nbg |"))
    assert "worse" in layer and "better" not in layer and "better" in nbg and "worse" not in nbg
    # an explicit --baseline still compares everything with that one
    assert {r["against"] for r in report.comparisons(results, "input @1spp")["rows"]} == {"input @1spp"}
    by = report.comparisons_by_kind(results)
    assert {r["label"]: r["against"] for r in by["rows"]}["layer"] == "input @8spp"
