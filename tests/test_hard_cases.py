"""The hard-case set (scene_gen.cases, configs/hard-cases.yaml, python -m training hard-cases): each case's
settings produce what it claims on real Mitsuba renders (24x24, a few spp), the case is recorded per
frame and read back, and the hard-case table is finite and names the stage, method and frame of a
planted non-finite output."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from stores.contract import FEATURE_GROUPS

RES = 24
SMALL = {"indoor_objects": 10, "outdoor_objects": 12, "material_palette": 4}
KINDS = {"fireflies": "indoor", "sun": "outdoor", "black": "indoor", "mirror": "indoor", "defocus": "outdoor",
         "motion": "outdoor", "zero-albedo": "indoor", "nan": "outdoor", "flat": "outdoor", "thin": "outdoor"}
FRAMES = {"mirror": 2, "motion": 2}
SEED = 5


def spec_of(case, seed=SEED, kind=None, res=RES):
    from pipeline.tasks import make_spec
    from scene_gen.spec import SceneSpec
    kind = kind or KINDS[case]
    return SceneSpec.from_json(make_spec(seed, kind, FRAMES.get(case, 1), (res, res), SMALL, case or ""))


def render_cfg(**kw):
    from pipeline.render import RenderConfig
    base = dict(res=(RES, RES), spp=4, layer_levels=2, ref_spp=64, ref_passes=8, ref_min_passes=8, time_slices=2)
    base.update(kw)
    return RenderConfig(**base)


_renders: dict = {}


def rendered(case, frame=0):
    """render_frame of the case's scene (cached per module)."""
    from pipeline.render import render_frame
    key = (case, frame)
    if key not in _renders:
        spec = spec_of(case)
        _renders[key] = (spec, render_frame(spec, frame, render_cfg()))
    return _renders[key]


def test_every_case_is_registered_and_documented():
    from scene_gen.cases import CASES
    assert set(CASES) == set(KINDS)
    for c in CASES.values():
        assert c.doc and c.scene_gen["p_defocus"] in (0.0,) and "p_motion" in c.scene_gen


def test_config_case_field_and_errors():
    from pipeline.config import DatasetConfig, load_config
    from pipeline.errors import ConfigError
    base = {"scenes": [{"kind": "indoor", "count": 1}]}
    plain = DatasetConfig.from_dict(base)
    assert "case" not in plain.to_dict()["scenes"][0]                 # old stores resume with the same dict
    assert plain.frames()[0].case == ""
    with_case = DatasetConfig.from_dict({"scenes": [{"kind": "indoor", "count": 1, "case": "black"}]})
    assert with_case.to_dict()["scenes"][0]["case"] == "black" and with_case.frames()[0].case == "black"
    assert DatasetConfig.from_dict(with_case.to_dict()) == with_case
    with pytest.raises(ConfigError, match=r"scenes\[0\]\.case: unknown hard case.*known: \['fireflies'"):
        DatasetConfig.from_dict({"scenes": [{"kind": "indoor", "count": 1, "case": "fireflys"}]})
    with pytest.raises(ConfigError, match="needs scenes of kind 'outdoor'"):
        DatasetConfig.from_dict({"scenes": [{"kind": "indoor", "count": 1, "case": "sun"}]})
    cfg = load_config("configs/hard-cases.yaml")
    assert {f.case for f in cfg.frames()} == set(KINDS)               # the set holds every case
    assert set(cfg.scene_splits()) == {"test"}


def test_graph_passes_the_case_only_when_set():
    from pipeline.config import DatasetConfig
    from pipeline.graph import build_graph
    cfg = DatasetConfig.from_dict({"scenes": [{"kind": "indoor", "count": 1},
                                              {"kind": "outdoor", "count": 1, "case": "thin"}]})
    specs = [n for n in build_graph(cfg, "/tmp/x.zarr").nodes.values() if n.stage == "spec"]
    assert [len(n.args) for n in specs] == [7, 8] and specs[1].args[-1] == "thin"   # (store, first frame, ...)


def test_spec_without_case_is_unchanged_and_case_round_trips():
    from scene_gen.sampling import sample_scene
    from scene_gen.config import SceneGenConfig
    from scene_gen.spec import SceneSpec
    plain = spec_of("", kind="indoor")
    assert plain.case == "" and '"case"' not in plain.to_json()
    assert plain == sample_scene(SEED, "indoor", res=RES, config=SceneGenConfig.from_dict(SMALL))
    s = spec_of("mirror")
    assert s.case == "mirror" and SceneSpec.from_json(s.to_json()) == s
    assert spec_of("mirror") == s                                     # deterministic


def test_black_has_no_light():
    spec, out = rendered("black")
    assert not spec.lights and all(o.emitter_radiance is None for o in spec.objects)
    assert not out["reference"].any() and not out["radiance"].any() and not out["layers"].any()


def test_sun_is_in_view_above_1e5():
    spec, out = rendered("sun")
    assert [lt.kind for lt in spec.lights] == ["sunsky"]
    assert out["reference"].max() > 1e5


def test_fireflies_tiny_bright_emitters_and_glass():
    from training.evaluate import FIREFLY_SHARE, firefly_share
    spec, out = rendered("fireflies")
    assert any(o.material.kind == "dielectric" for o in spec.objects if o.name == "case_glass")
    assert out["radiance"].max() >= 1e4
    share = firefly_share(torch.from_numpy(out["radiance"]).permute(2, 3, 0, 1),
                          torch.from_numpy(out["reference"]).permute(2, 0, 1))
    assert share >= FIREFLY_SHARE


def test_mirror_moves_and_reflects():
    spec, _ = rendered("mirror")
    _, out = rendered("mirror", 1)
    assert spec.has_motion and spec.cameras[0].origin != spec.cameras[1].origin
    spec_c = out["features"][..., FEATURE_GROUPS["specular"]].mean(axis=2)
    assert (np.abs(spec_c - 0.95).max(-1) < 1e-3).mean() > 0.1        # the mirror covers the view
    assert np.abs(out["guides_motion"]).max() > 0.1                     # camera and objects move


def test_defocus_is_extreme():
    spec, out = rendered("defocus")
    assert out["meta"]["has_defocus"]
    assert np.abs(out["features"][..., FEATURE_GROUPS["coc"]]).max() > 0.1 * RES


def test_motion_is_fast():
    spec, out = rendered("motion")
    assert out["meta"]["has_motion"]
    assert np.abs(out["guides_motion"]).max() > 0.1 * RES


def test_zero_albedo_surfaces():
    from scene_gen.cases import BLACK
    spec, out = rendered("zero-albedo")
    assert spec.objects[0].material == BLACK
    hit = out["guides_depth"][..., 0] > 0
    zero = (out["features"][..., FEATURE_GROUPS["albedo"]] == 0).all(-1).all(-1)
    assert hit.mean() > 0.9 and zero[hit].mean() > 0.25


def test_nan_from_the_renderer_is_counted_and_replaced():
    spec, out = rendered("nan")
    m = out["meta"]
    assert m["case"] == "nan" == spec.case
    assert m["nonfinite_inputs"] > 0 and m["nonfinite_layers"] > 0 and m["nonfinite_reference"] > 0
    assert m["nonfinite_expected"] is True              # the case declares it (Case.nonfinite)
    for k in ("radiance", "features", "layers", "reference", "reference_stderr", "guides_albedo", "guides_normal",
              "guides_depth", "guides_motion"):
        assert np.isfinite(out[k]).all(), k


def test_flat_is_mostly_one_plane():
    spec, out = rendered("flat")
    n = np.round(out["guides_normal"].reshape(-1, 3), 3)
    _, counts = np.unique(n, axis=0, return_counts=True)
    assert counts.max() / len(n) > 0.6


def test_thin_is_one_pixel_wide():
    spec, out = rendered("thin")
    y = out["reference"].mean(-1)
    bright = y > 0.5 * y.max()
    assert y.max() > 5 and (bright.sum(axis=0) == 1).mean() > 0.9     # one pixel in (nearly) every column
    assert len(np.nonzero(bright.any(axis=1))[0]) == 1                 # ... in one row


# ------------------------------------------------------------------------------------------------
# the store tag and the hard-cases command

@pytest.fixture(scope="module")
def case_store(tmp_path_factory):
    """A store of real 16x16 renders: black, thin, nan and one ordinary frame whose SceneSpec JSON has
    no case (as in stores made before cases existed)."""
    from pipeline.render import render_frame
    from stores.schema import StoreLayout
    from stores.writer import open_or_create
    frames = []
    for case in ("black", "thin", "nan", ""):
        spec = spec_of(case, kind=KINDS.get(case, "outdoor"), res=16)
        frames.append(render_frame(spec, 0, render_cfg(res=(16, 16), spp=2, ref_spp=32)))
    path = tmp_path_factory.mktemp("hc") / "hard.zarr"
    layout = StoreLayout(num_frames=len(frames), height=16, width=16, spp=2, layer_spp=(1, 2), tile=16)
    w = open_or_create(str(path), layout, {"test": True})
    for i, fr in enumerate(frames):
        w.write_frame(i, fr)
    return str(path)


def test_a_case_declares_its_loaded_scene_edit_and_whether_nan_is_its_purpose():
    """Cases are a registry: what a case does to the loaded scene and whether non-finite samples are its
    purpose are declared with it, and nothing outside its own file names a case (the ``nan`` one)."""
    import ast
    from pathlib import Path

    from scene_gen.cases import CASES, nonfinite_expected
    assert [n for n, c in CASES.items() if c.loaded is not None] == ["nan"]
    assert [n for n, c in CASES.items() if c.nonfinite] == ["nan"]
    assert nonfinite_expected("black,nan") and not nonfinite_expected("black") and not nonfinite_expected("")
    root = Path(__file__).resolve().parent.parent
    named = []
    for pkg in ("core", "scene_gen", "stores", "pipeline", "training", "studies"):
        for p in (root / pkg).rglob("*.py"):
            if p == root / "scene_gen" / "cases.py":
                continue
            tree = ast.parse(p.read_text())
            number = {id(c.args[0]) for c in ast.walk(tree) if isinstance(c, ast.Call) and c.args
                      and getattr(c.func, "id", "") == "float"}             # float("nan"): a number, not the case
            named += [f"{p.relative_to(root)}:{n.lineno}" for n in ast.walk(tree)
                      if isinstance(n, ast.Constant) and n.value == "nan" and id(n) not in number]
    assert not named, f"the nan case named outside scene_gen/cases.py: {named}"


def test_a_store_made_before_frames_nonfinite_expected_gets_it_on_resume(case_store, tmp_path):
    """An older store (no frames/nonfinite_expected) reads it as False, so its nan-case frame is flagged;
    the dataset run's resume adds the column and records the frames whose case makes NaN on purpose."""
    import shutil

    from pipeline.dataset import record_intended_nonfinite
    from stores.reader import frame_problems, open_store
    from stores.writer import open_or_create
    old = tmp_path / "old.zarr"
    shutil.copytree(case_store, old)
    shutil.rmtree(old / "frames" / "nonfinite_expected")
    assert any("NaN/Inf values" in p for p in frame_problems(str(old), 2))          # frame 2: the nan case
    open_or_create(str(old), open_store(str(old)).layout, {"test": True})          # a resume adds the column
    assert record_intended_nonfinite(str(old)) == [2] and record_intended_nonfinite(str(old)) == []
    assert frame_problems(str(old), 2) == [] and frame_problems(case_store, 2) == []


def test_frames_case_written_and_read_back(case_store, tmp_path):
    import shutil
    from stores.reader import open_store
    from training.hardcases import frame_cases
    assert list(open_store(case_store).meta_column("case")) == ["black", "thin", "nan", ""]    # frames/case
    assert frame_cases(case_store) == ["black", "thin", "nan", ""]
    old = tmp_path / "old.zarr"                      # a store made before frames/case existed (and so
    shutil.copytree(case_store, old)                 # before frames/kind, which came after it)
    shutil.rmtree(old / "frames" / "case")
    shutil.rmtree(old / "frames" / "kind")
    assert list(open_store(str(old)).meta_column("case")) == [""] * 4
    assert frame_cases(str(old)) == ["black", "thin", "nan", ""]       # from the SceneSpec JSON


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """A tiny layer run trained for 2 steps, and a copy whose weights hold a NaN (a planted non-finite output)."""
    from test_training import TINY, make_store
    from training import checkpoint as ckpt
    from training.__main__ import main
    root = tmp_path_factory.mktemp("runs")
    train = make_store(root / "train.zarr", h=16, w=16, per_split=(2, 1, 1))
    assert main(["train", "--model", "layer", "--store", train, "--steps", "2", "--crop", "16", "--batch", "1",
                 "--spp", "2", "--out", str(root / "good"), "--model-cfg", json.dumps(TINY), "--no-progress",
                 "--val-every", "2", "--val-frames", "1", "--workers", "0"]) == 0
    ck = ckpt.load(root / "good" / "checkpoint.pt")
    name = next(iter(ck["state_dict"]))
    ck["state_dict"][name] = torch.full_like(ck["state_dict"][name], float("nan"))
    (root / "poisoned").mkdir()
    torch.save(ck, root / "poisoned" / "checkpoint.pt")
    return root


def test_hard_cases_command(case_store, runs, tmp_path, capsys):
    from training.__main__ import main
    out = tmp_path / "report"
    # the poisoned run's non-finite outputs are problems found: exit 1
    assert main(["hard-cases", "--store", case_store, "--runs", str(runs / "good"), str(runs / "poisoned"),
                 str(runs / "missing"), "--out", str(out)]) == 1
    assert "problem(s) found" in capsys.readouterr().err
    # strict JSON (the perfect PSNR is null): parsers other than Python's refuse NaN and Infinity
    res = json.loads((out / "hard-cases.json").read_text(), parse_constant=lambda c: pytest.fail(f"{c} in JSON"))
    md = (out / "hard-cases.md").read_text()
    assert res["methods"] == ["good", "poisoned", "input", "oidn"]
    assert set(res["cases"]) == {"black", "thin", "nan", "(none)"}
    for case in ("black", "thin", "nan", "(none)"):
        for m in ("good", "input", "oidn"):
            v = res["cases"][case][m]
            assert v["finite"] and np.isfinite(v["relmse"]), (case, m)
            # an exact output (the input, black on black) has an infinite PSNR: null in strict JSON
            assert (v["psnr"] is None) if (case, m) == ("black", "input") else \
                (v["psnr"] is None and case == "black" or np.isfinite(v["psnr"])), (case, m)
        assert not res["cases"][case]["poisoned"]["finite"]
    assert res["cases"]["black"]["input"]["relmse"] == 0.0
    flags = res["flags"]
    planted = [f for f in flags if f["method"] == "poisoned" and f["stage"] == "model output"]
    assert {f["frame"] for f in planted} == {0, 1, 2, 3} and all(f["kind"] == "non-finite" for f in planted)
    assert not [f for f in flags if f["method"] == "good" and f["kind"] == "non-finite"]
    # the nan frame: the renderer's NaN named by store stage, and the methods evaluated on what the store
    # made of it (finite)
    stages = {f["stage"] for f in flags if f["method"] == "store" and f["frame"] == 2}
    assert stages == {"inputs", "layers", "reference"}
    assert not any(f["kind"] == "not evaluated" for f in flags)
    assert "stage *model output*, method `poisoned`" in md and "| thin | finite |" in md
    assert "| black | finite | " in md and " / inf |" in md      # the table shows the perfect PSNR as inf
    # each method against its own noisy input (the run reads 2 spp per sample: the input at 2 spp)
    assert res["methods_info"]["good"]["input_label"] == "input" and res["methods_info"]["input"]["input_label"] is None
    assert res["cases"]["black"]["good"]["vs_input"]["verdict"] in ("exact", "not exact")
    assert "vs_input" not in res["cases"]["thin"]["input"] and "relmse_ci95" in res["cases"]["thin"]["good"]
    assert "Against its own noisy input" in md
    # without the poisoned run nothing is wrong: the nan frame's replaced NaN are its case's purpose
    assert main(["hard-cases", "--store", case_store, "--runs", str(runs / "good"), "--no-oidn",
                 "--out", str(tmp_path / "good")]) == 0


def test_outlier_rule():
    from training.hardcases import summarize
    rows = [{"index": i, "relmse": e, "psnr": 30.0, "finite": True} for i, e in enumerate([0.01, 0.012, 0.011, 0.5])]
    res = summarize([{"label": "m", "frames": rows}], ["a", "b", "c", "d"], [])
    assert [(f["case"], f["frame"], f["kind"]) for f in res["flags"]] == [("d", 3, "error")]
    res = summarize([{"label": "m", "frames": rows[:3]}], ["a", "b", "c"], [])
    assert res["flags"] == []


def test_each_method_is_judged_against_its_own_input_with_intervals():
    """Six frames of a case in three clips: a method far below its input is better, one above it worse, one
    level with it shows no difference; where the input is exact, a method is exact or not."""
    from training.hardcases import hard_case_table, link_inputs, summarize
    rng = np.random.default_rng(0)

    def ev(label, method, rel, psnr, spp=1, kind="pixels"):
        rows = [{"index": i, "clip": i // 2, "relmse": max(rel + rng.normal(0, 0.01), 0.0) if rel else 0.0,
                 "psnr": psnr + rng.normal(0, 0.1) if np.isfinite(psnr) else psnr, "finite": True} for i in range(6)]
        return {"label": label, "method": method, "spp": spp, "input_kind": kind, "frames": rows}
    noisy = ev("input", "input", 1.0, 20.0)
    same = {**noisy, "label": "same", "method": "nbg", "frames": [dict(r) for r in noisy["frames"]]}
    for r, sign in zip(same["frames"], (1, -1, -1, 1, 1, -1)):      # level with the input: +-0.05 per clip
        r["relmse"] += 0.05 * sign
    evals = [ev("good", "nbg", 0.2, 25.0), ev("bad", "nbg", 2.0, 15.0), same, noisy,
             ev("other", "layer", 0.1, 30.0, spp=8, kind="samples"), ev("input @8spp", "input", 0.5, 22.0, spp=8)]
    link_inputs(evals)
    assert [e.get("input_label") for e in evals] == ["input", "input", "input", None, "input @8spp", None]
    res = summarize(evals, ["a"] * 6, [])
    cell = res["cases"]["a"]
    assert cell["good"]["vs_input"]["verdict"] == "beats" and cell["bad"]["vs_input"]["verdict"] == "worse"
    assert cell["same"]["vs_input"]["verdict"] == "not shown"
    d = cell["good"]["vs_input"]["relmse"]
    assert d["mean"] == pytest.approx(-0.8, abs=0.02) and d["ci95"][1] < 0 and cell["good"]["vs_input"]["frames"] == 6
    assert cell["other"]["vs_input"]["input"] == "input @8spp"
    lo, hi = cell["good"]["relmse_ci95"]
    assert lo < cell["good"]["relmse"] < hi
    md = hard_case_table(res)
    assert ": better" in md and ": **worse**" in md and "no difference shown" in md
    black = [ev("zero", "nbg", 0.0, float("inf")), ev("leak", "nbg", 0.1, 40.0), ev("input", "input", 0.0, float("inf"))]
    link_inputs(black)
    cell = summarize(black, ["black"] * 6, [])["cases"]["black"]
    assert cell["zero"]["vs_input"]["verdict"] == "exact" and cell["leak"]["vs_input"]["verdict"] == "not exact"


def test_a_split_whose_every_frame_is_flagged_is_listed_not_fatal(tmp_path, capsys):
    """Every frame of the test split flagged by validate (a negative reference stderr, written through zarr-python):
    `hard-cases`, which exists to look at hard frames, evaluates the other splits, lists each flagged frame in its
    table as not evaluated and exits 1 with one line saying so (before: exit 2, 'every frame of split ... is
    flagged', no table). With every frame of the store flagged it still writes the table of them, exit 1."""
    from stores.reader import open_store
    from test_training import _zarr_set, make_store
    from training.__main__ import main
    path = make_store(tmp_path / "s.zarr", h=16, w=16, per_split=(1, 1, 2))
    st = open_store(path)
    test = st.frames_in_split("test")
    for i in test:
        _zarr_set(path, "reference/stderr", (i, 0, 1, 1), -0.5)
    out = tmp_path / "hc"
    assert main(["hard-cases", "--store", path, "--out", str(out), "--no-oidn"]) == 1
    err = capsys.readouterr().err
    assert "split 'test'" in err and "every frame" in err and "Traceback" not in err, err
    res = json.loads((out / "hard-cases.json").read_text())
    left = {f["frame"]: f for f in res["flags"] if f["kind"] == "not evaluated"}
    assert set(left) == set(test) and all("negative" in f["detail"] for f in left.values()), left
    assert {r["index"] for r in res["frames"]["input"]} == set(range(st.num_frames)) - set(test)
    md = (out / "hard-cases.md").read_text()
    assert all(f"frame {i}: stage *evaluate*" in md for i in test), md
    for i in set(range(st.num_frames)) - set(test):
        _zarr_set(path, "reference/stderr", (i, 0, 1, 1), -0.5)
    assert main(["hard-cases", "--store", path, "--out", str(out), "--no-oidn"]) == 1
    err = capsys.readouterr().err
    assert "every frame" in err and "Traceback" not in err, err
    res = json.loads((out / "hard-cases.json").read_text())
    assert {f["frame"] for f in res["flags"] if f["kind"] == "not evaluated"} == set(range(st.num_frames))
