"""pipeline.tasks: the three stream tasks and the whole-frame task give identical bytes, whether the
worker's loaded scene is reused or each task loads its own."""
from __future__ import annotations

import numpy as np

from scene_gen.config import SceneGenConfig
from stores.contract import FRAME_ARRAYS

RENDER = {"res": [12, 8], "spp": 4, "layer_levels": 3, "ref_spp": 32, "ref_passes": 4, "ref_min_passes": 2,
          "time_slices": 2, "ref_time_slices": 2}


def _spec_json():
    from pipeline import tasks
    # a clip with motion: time slices move objects, and a reused scene must be back at rest
    sg = SceneGenConfig(outdoor_objects=6, p_motion=1.0, material_palette=2).to_dict()
    return tasks.make_spec(5, "outdoor", 2, (12, 8), sg)


def test_cached_scene_gives_the_bytes_of_fresh_loads(mi):
    from pipeline import tasks
    spec = _spec_json()
    tasks.clear_scene_cache()
    with tasks.frame_scene(spec, 1, RENDER) as fs:
        first = fs
        assert fs.load_seconds > 0 and fs.has_motion
    with tasks.frame_scene(spec, 1, RENDER) as fs:
        assert fs is first and fs.load_seconds == 0.0          # the worker's warm scene
    cached = [tasks.render_inputs(spec, 1, RENDER), tasks.render_layers(spec, 1, RENDER),
              tasks.render_reference(spec, 1, RENDER)]
    fresh = []
    for fn in (tasks.render_inputs, tasks.render_layers, tasks.render_reference):
        tasks.clear_scene_cache()
        fresh.append(fn(spec, 1, RENDER))
    a = tasks.assemble(spec, 1, *cached)
    b = tasks.assemble(spec, 1, *fresh)
    tasks.clear_scene_cache()
    whole = tasks.render_whole_frame(spec, 1, RENDER)
    for k in FRAME_ARRAYS:
        assert a[k].tobytes() == b[k].tobytes() == whole[k].tobytes(), k
    assert a["meta"]["has_motion"] and a["meta"]["reference_spp"] == 32
    assert {k: v for k, v in a["meta"].items() if k != "render_seconds"} == \
        {k: v for k, v in whole["meta"].items() if k != "render_seconds"}
    assert np.abs(a["features"][..., 11:13]).max() > 0           # objects really moved


def test_cache_holds_a_bounded_number_of_scenes(mi):
    from pipeline import tasks
    spec = _spec_json()
    tasks.clear_scene_cache()
    for frame in (0, 1, 0, 1):
        with tasks.frame_scene(spec, frame, RENDER):
            pass
    with tasks.frame_scene(spec, 0, dict(RENDER, spp=2)):
        pass
    assert len(tasks._scenes) == tasks.SCENE_CACHE_SIZE
    tasks.clear_scene_cache()
    assert not tasks._scenes
