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
    assert a["meta"]["scene_json"] == spec and "scene_json" not in whole["meta"]   # the write task has it
    assert {k: v for k, v in a["meta"].items() if k not in ("render_seconds", "scene_json")} == \
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


def _max_kernel_ops(fn) -> int:
    import drjit as dr
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    dr.kernel_history_clear()
    try:
        fn()
        return max(k.get("operation_count", 0) for k in dr.kernel_history())
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)


def test_a_new_scene_loads_after_the_cached_one_is_freed(mi):
    """drjit traces a virtual call for every instance alive in the process: a scene still cached when
    the next loads would grow all of the next one's kernels (and their compile time)."""
    import gc
    from pipeline import tasks
    sg = SceneGenConfig(outdoor_objects=6, material_palette=2).to_dict()
    a, b = (tasks.make_spec(seed, "outdoor", 1, (12, 8), sg) for seed in (5, 6))
    tasks.clear_scene_cache()
    gc.collect()
    alone = _max_kernel_ops(lambda: tasks.render_inputs(b, 0, RENDER))
    tasks.clear_scene_cache()
    tasks.render_inputs(a, 0, RENDER)
    assert len(tasks._scenes) == 1
    after = _max_kernel_ops(lambda: tasks.render_inputs(b, 0, RENDER))
    assert len(tasks._scenes) == 1
    # the measure sees a live scene: with a's scene held elsewhere, b's kernels grow
    tasks.clear_scene_cache()
    from pipeline.render import FrameScene
    from scene_gen.spec import SceneSpec
    held = FrameScene(SceneSpec.from_json(a), 0, tasks._render_cfg(RENDER))
    bloated = _max_kernel_ops(lambda: tasks.render_inputs(b, 0, RENDER))
    del held
    tasks.clear_scene_cache()
    assert bloated > 1.2 * alone
    # (drjit's operation count of one kernel can vary by a few per cent between calls; a's scene is more)
    assert after < alone + (bloated - alone) / 2, (alone, after, bloated)
