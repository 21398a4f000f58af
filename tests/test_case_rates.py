"""Hard cases drawn at rates (``cases:`` of a scene group, pipeline.config.draw_case) and the held-out seed
space (``held_out: true``): the rates are met (a binomial check over many scenes), a scene's case is a
function of its seed alone (whatever the workers, the task order or the listing order), bad rates are one
line, and no dataset that is not held out draws a held-out scene."""
from __future__ import annotations

import subprocess
import sys
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import yaml
import zarr
from scipy.stats import binomtest

from pipeline.config import DatasetConfig, load_config
from pipeline.groups import HELD_OUT_SEEDS, draw_case, scene_seed
from pipeline.errors import ConfigError

ROOT = Path(__file__).resolve().parent.parent
RATES = {"sun": 0.1, "fireflies": 0.1, "zero-albedo": 0.1, "thin": 0.05}


def test_each_case_is_drawn_at_its_rate():
    n = 4000
    cfg = DatasetConfig.from_dict({"seed": 3, "scenes": [{"kind": "outdoor", "count": n, "cases": RATES}]})
    got = Counter(f.case for f in cfg.frames())
    assert set(got) == set(RATES) | {""}
    for case, rate in {**RATES, "": 1 - sum(RATES.values())}.items():
        assert binomtest(got[case], n, rate).pvalue > 1e-3, (case, got[case], n * rate)


def test_a_combination_is_one_key_and_a_rate_of_0_never_draws():
    cfg = DatasetConfig.from_dict({"seed": 1, "scenes": [
        {"kind": "outdoor", "count": 400, "cases": {"sun,fireflies": 0.5, "thin": 0.0}}]})
    got = Counter(f.case for f in cfg.frames())
    assert set(got) == {"sun,fireflies", ""} and binomtest(got["sun,fireflies"], 400, 0.5).pvalue > 1e-3


def test_a_scenes_case_is_a_function_of_its_seed_and_the_rates_alone():
    cfg = DatasetConfig.from_dict({"seed": 9, "scenes": [{"kind": "indoor", "count": 3},
                                                         {"kind": "outdoor", "count": 200, "frames": 2, "cases": RATES}]})
    reordered = DatasetConfig.from_dict({"seed": 9, "scenes": [
        {"kind": "indoor", "count": 3},
        {"kind": "outdoor", "count": 200, "frames": 2, "cases": dict(reversed(list(RATES.items())))}]})
    frames = cfg.frames()
    assert [f.case for f in frames] == [f.case for f in reordered.frames()]          # the listing order: none
    for f in frames:
        assert f.case == (draw_case(f.seed, RATES) if f.scene >= 3 else "")
    by_scene = {}
    for f in frames:
        by_scene.setdefault(f.scene, set()).add(f.case)
    assert all(len(c) == 1 for c in by_scene.values())                                # a clip keeps one case
    assert DatasetConfig.from_dict(cfg.to_dict()) == cfg and cfg.to_dict()["scenes"][1]["cases"] == RATES


@pytest.mark.parametrize("group, needle", [
    ({"cases": {"sunn": 0.1}}, r"scenes\[0\]\.cases\.sunn: unknown hard case\(s\) \['sunn'\]; known: \["),
    ({"cases": {"sun": 1.5}}, r"scenes\[0\]\.cases\.sun must be a rate in \[0, 1\], got 1\.5"),
    ({"cases": {"sun": -0.1}}, r"scenes\[0\]\.cases\.sun must be a rate in \[0, 1\]"),
    ({"cases": {"sun": "often"}}, r"scenes\[0\]\.cases\.sun must be a rate in \[0, 1\]"),
    ({"cases": {"sun": 0.6, "thin": 0.5}}, r"scenes\[0\]\.cases: the rates sum to 1\.1, above 1; .* sum to at most 1"),
    ({"cases": {"sun": 0.5000001, "thin": 0.5}}, r"scenes\[0\]\.cases: the rates sum to 1\.0000001, above 1"),
    ({"cases": [0.1]}, r"scenes\[0\]\.cases must be a mapping of hard-case names"),
    ({"cases": {"sun": 0.1}, "case": "thin"}, r"scenes\[0\]: give case \(every scene\) or cases"),
    ({"kind": "indoor", "cases": {"sun": 0.1}}, r"scenes\[0\]\.cases\.sun: hard case 'sun' needs scenes of kind"),
])
def test_bad_rates_are_a_one_line_config_error(group, needle):
    with pytest.raises(ConfigError, match=needle) as e:
        DatasetConfig.from_dict({"scenes": [{"kind": "outdoor", "count": 2, **group}]})
    assert "\n" not in str(e.value)


def test_held_out_scenes_come_from_a_seed_space_no_other_dataset_draws(real_scene_data):
    assert all(0 <= scene_seed(r, i) < HELD_OUT_SEEDS for r in (0, 7, 2 ** 62) for i in range(200))
    assert all(HELD_OUT_SEEDS <= scene_seed(r, i, True) < 2 ** 32 for r in (0, 14) for i in range(200))
    suite = load_config(ROOT / "configs" / "hard-cases.yaml")
    assert suite.held_out and set(suite.scene_splits()) == {"test"}
    assert all(f.seed >= HELD_OUT_SEEDS for f in suite.frames())
    for path in sorted((ROOT / "configs").glob("*.yaml")):           # every shipped dataset config
        d = yaml.safe_load(path.read_text())
        for data in ([d] if "scenes" in d else [d[k] for k in ("train_data", "heldout_data") if isinstance(d.get(k), dict)]):
            cfg = DatasetConfig.from_dict(data)
            if not cfg.held_out:
                assert all(f.seed < HELD_OUT_SEEDS for f in cfg.frames()), path.name
    with pytest.raises(ConfigError, match="held_out: a held-out dataset is for evaluation only"):
        DatasetConfig.from_dict({"held_out": True, "split": {"train": 1}, "scenes": [{"kind": "indoor", "count": 1}]})
    plain = DatasetConfig.from_dict({"held_out": True, "scenes": [{"kind": "indoor", "count": 2}]})
    assert plain.split == {"test": 1.0} and set(plain.scene_splits()) == {"test"}


def test_training_refuses_a_held_out_store():
    from training.errors import DataError
    from training.loop import refuse_held_out

    class Store:
        path = "data/hard-cases.zarr"
        config = {"name": "hard-cases", "held_out": True}
    with pytest.raises(DataError, match="held-out store .*evaluation only, never for training"):
        refuse_held_out(Store())
    Store.config = {"name": "train"}
    refuse_held_out(Store())


def test_the_drawn_cases_are_the_same_whatever_the_workers(tmp_path):
    """Two renders of a config that draws cases, on one worker and on two: frames/case and every scene's
    SceneSpec agree (8x8, 2 spp: seconds)."""
    d = {"name": "rates", "seed": 21, "resolution": 8, "scenes": [
        {"kind": "outdoor", "count": 4, "cases": {"sun": 0.3, "thin": 0.3}}],
        "render": {"spp": 2, "layer_levels": 1, "ref_spp": 8, "ref_passes": 2, "ref_min_passes": 2},
        "scene_gen": {"outdoor_objects": 4}, "split": {"train": 1},
        "cluster": {"kind": "local", "dashboard_address": None}}
    (tmp_path / "c.yaml").write_text(yaml.safe_dump(d))
    want = [f.case for f in DatasetConfig.from_dict(d).frames()]
    assert len(set(want)) >= 2                       # the seed gives both kinds of scene
    got = {}
    for n in (1, 2):
        out = tmp_path / f"w{n}.zarr"
        r = subprocess.run([sys.executable, "-m", "pipeline", "dataset", "--config", str(tmp_path / "c.yaml"),
                            "--out", str(out), "--workers", str(n), "--no-progress"], cwd=ROOT, capture_output=True,
                           text=True, timeout=600)
        assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
        g = zarr.open_group(str(out), mode="r")
        got[n] = ([str(c) for c in g["frames/case"][:]], [str(s) for s in g["frames/scene_json"][:]],
                  np.asarray(g["inputs/radiance"][:]).tobytes())
    assert got[1][0] == want and got[1] == got[2]
