"""``python -m studies bench-scale`` (studies.bench_scale) at tiny sizes: it renders its source store
(configs/smoke.yaml through ``python -m pipeline dataset``), writes stores of stills, long clips and
pairs from its frames, and times every consumer; the figures are meaningless here, the stages are not."""
from __future__ import annotations

import math

import numpy as np


def test_every_consumer_is_timed_at_every_size_and_layout():
    from studies import bench_scale as B
    table = B.run(frames=(16, 24), say=lambda *a, **k: None)
    consumers = {f"datasets_{k}" for k in B.KINDS} | {"evaluate", "hard_cases", "report", "export_exr",
                                                      "export_layerdenoise", "export_oidn"}
    assert set(table) == {"stills", "clips", "pairs"}
    assert set(table["stills"]) == set(table["clips"]) == consumers and set(table["pairs"]) == {"export_noisebase"}
    for layout, stages in table.items():
        for stage, per in stages.items():
            assert set(per) == {16, 24} and all(math.isfinite(v) and v > 0 for v in per.values()), (layout, stage, per)
    md = B.markdown(table)
    assert "| stills | 16 | 24 | 24 / 16 |" in md and "| export_noisebase |" in md


def test_the_stores_hold_what_the_layouts_say(tmp_path):
    """Stills: a clip a frame; clips: two halves, one train and one test; pairs: clips of two frames that
    are the source clip itself (its seed), so the Noisebase export can re-trace them."""
    from stores.reader import open_store
    from studies import bench_scale as B
    source = B.source_store(tmp_path)
    src = open_store(source)
    clip_seed = int(src.meta_column("scene_seed")[int(np.argmax(src.meta_column("num_frames")))])
    for layout in B.LAYOUTS:
        st = open_store(B.build_store(source, str(tmp_path / f"{layout}.zarr"), 20, layout))
        clips = st.clips(None)
        lengths = sorted(len(c) for c in clips.values())
        assert st.num_frames == 20 and st.complete_frames() == list(range(20))
        assert lengths == {"stills": [1] * 20, "clips": [10, 10], "pairs": [2] * 10}[layout], (layout, lengths)
        cases = [str(c) for c in st.meta_column("case")]
        assert cases[0] == "fireflies" and cases[10] == "sun_in_view" and cases.count("") == 18
        if layout == "clips":
            assert {st.split_of_frame(0), st.split_of_frame(19)} == {"train", "test"}
            assert st.scene_json(19).count('"origin"') == 10          # a camera a frame of the clip
        if layout == "pairs":
            assert set(int(s) for s in st.meta_column("scene_seed")) == {clip_seed}


def test_a_size_without_a_test_frame_is_one_line_naming_frames_before_anything_renders(capsys):
    """``--frames 0`` (no store to time) and ``--frames -5`` are argument errors naming ``--frames`` and
    the fewest frames every layout can be built with (16: stills' first test clip is frame 7, pairs'
    frames 14 and 15), exit 2, before the source store is rendered."""
    from studies import bench_scale as B
    from studies.__main__ import main
    assert B.min_frames() == 16 and B.min_frames(("clips",)) == 4
    for bad in ("0", "-5", "15"):
        assert main(["bench-scale", "--frames", "100", bad]) == 2
        err = capsys.readouterr().err
        assert err == ("error: --frames must be one or more integers >= 16 (the fewest frames at which "
                       f"every layout has a clip in the train and the test split), got {bad}\n"), err


def test_training_bench_has_no_scale_and_names_the_studies_command(capsys):
    """It renders as well as it reads: training's bench says in one line where it went, and starts nothing."""
    from training.__main__ import main
    assert main(["bench", "--scale", "--frames", "100"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "`python -m studies bench-scale`" in err, err
