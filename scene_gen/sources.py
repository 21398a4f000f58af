"""Where a scene comes from, behind one call: :func:`load_frame` turns a scene's description into the loaded
scene a renderer asks (``scene_gen.to_mitsuba.LoadedScene``), whether the generator described it
(``scene_gen.to_mitsuba``) or it is a user's Mitsuba scene file (``scene_gen.scene_files``, a spec with a
``source``)."""
from __future__ import annotations

from scene_gen import scene_files, to_mitsuba
from scene_gen.spec import SceneSpec


def load_frame(spec: SceneSpec, frame: int, res, *, rfilter: str = "box", merge: bool = True, on_loaded=None):
    """Frame ``frame`` of ``spec`` loaded at film ``res`` (W, H) with the pixel filter ``rfilter``; ``merge``
    (generated scenes): static objects sharing a material are one mesh; ``on_loaded(scene)`` may edit
    the loaded ``mi.Scene`` before anything renders (tests)."""
    res = (res, res) if isinstance(res, int) else (int(res[0]), int(res[1]))
    if spec.source is not None:
        return scene_files.load_frame(spec, frame, res, rfilter=rfilter, on_loaded=on_loaded)
    return to_mitsuba.load_frame(spec, frame, res, merge=merge, on_loaded=on_loaded, rfilter=rfilter)
