"""The held-out real-scene suite's files (``scene_gen.real_scenes``) and its config: written the same bytes
every time, each loading in Mitsuba, the Cornell box file rendering what ``mi.cornell_box()`` renders, and
``configs/real-scenes.yaml`` a held-out dataset of those files only."""
from __future__ import annotations

import numpy as np

from scene_gen.real_scenes import SUITE


def test_the_suite_is_written_the_same_every_time_and_loads(mi, tmp_path):
    from scene_gen.real_scenes import write_suite
    from scene_gen.scene_files import content_hash, has_sensor
    a = write_suite(tmp_path / "a")
    b = write_suite(tmp_path / "b")
    assert [p.stem for p in a] == list(SUITE)
    for p, q in zip(a, b):
        assert content_hash(p) == content_hash(q) and has_sensor(p), p.name
    text = {p.stem: p.read_text() for p in a}
    assert 'type="bitmap"' in text["textured-interior"] and 'type="envmap"' in text["envmap-object"]
    assert 'type="roughconductor"' in text["metals"] and 'type="dielectric"' in text["glass"]
    assert 'type="roughdielectric"' in text["glass"] and 'type="thindielectric"' in text["glass"]
    # the Cornell box file renders Mitsuba's own Cornell box (image and 4x4-block means, per channel)
    from_file = mi.load_file(str(tmp_path / "a" / "cornell-box.xml"))
    d = mi.cornell_box()
    d["sensor"]["film"] = {"type": "hdrfilm", "width": 128, "height": 128, "rfilter": {"type": "gaussian"}}
    from_dict = mi.load_dict(d)
    runs = {k: np.stack([np.asarray(mi.render(s, spp=16, seed=i), np.float64)[..., :3] for i in range(4)])
            for k, s in (("file", from_file), ("dict", from_dict))}
    blocks = lambda x: x.reshape(x.shape[0], 16, 8, 16, 8, 3).mean(axis=(2, 4))     # noqa: E731
    for agg in (lambda x: x.mean(axis=(1, 2)), blocks):
        a_, b_ = agg(runs["file"]), agg(runs["dict"])
        z = (a_.mean(0) - b_.mean(0)) / np.sqrt(a_.var(0, ddof=1) / 4 + b_.var(0, ddof=1) / 4 + 1e-12)
        assert np.abs(z).max() < 5.5 and np.mean(np.abs(z) > 3) < 0.02, np.abs(z).max()


def test_the_real_scene_config_is_a_held_out_dataset_of_the_suite(tmp_path, monkeypatch):
    from pathlib import Path

    from pipeline.config import load_config
    from scene_gen.real_scenes import write_suite
    monkeypatch.setenv("DENOISE_DATA", str(tmp_path))
    write_suite(tmp_path / "real-scenes")
    root = Path(__file__).resolve().parent.parent
    box = load_config(root / "configs" / "real-scenes.yaml")
    gauss = load_config(root / "configs" / "real-scenes.yaml", ["render.filter=gaussian", "name=real-scenes-gaussian"])
    assert box.held_out and box.split_fractions == {"test": 1.0} and box.render_config().filter == "box"
    assert gauss.render_config().filter == "gaussian" and gauss.name == "real-scenes-gaussian"
    frames = box.frames()
    names = {Path(f.source["path"]).stem for f in frames}
    assert names == set(SUITE) and all(f.kind == "file" for f in frames)
    per_scene = {n: sum(Path(f.source["path"]).stem == n for f in frames) for n in names}
    assert set(per_scene.values()) == {3}                   # its own sensor and two views around it: an interval each
    assert box.content_dict() != gauss.content_dict()
