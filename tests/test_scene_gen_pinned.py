"""Existing datasets keep their scenes: the SceneSpec bytes of fixed (kind, seed) pairs, pinned.

A store records each scene's seed and kind, and resuming or extending it regenerates scenes from
them, so a refactor of the generator must not change one byte of a spec (nor of a room mesh, the one
mesh kind ``scene_gen`` builds itself). The hashes below are the sha256 of ``SceneSpec.to_json()``
(and of ``MeshData.digest()``) as the generator made them when they were recorded; a change of the
scenes on purpose is a new dataset and updates them. To print the current values:

    .venv/bin/python tests/test_scene_gen_pinned.py
"""
from __future__ import annotations

import hashlib

import pytest

from scene_gen import meshes
from scene_gen.config import SceneGenConfig
from scene_gen.sampling import sample_scene

# (kind, seed, frames, config): a still, a clip, a large seed, and non-default settings (defocus,
# motion, a palette, the sky and the object counts of both families)
SMALL = {"indoor_objects": 12, "outdoor_objects": 15, "p_sunsky": 1.0, "p_motion": 1.0, "p_defocus": 1.0,
         "material_palette": 3}
SCENES = {
    ("indoor", 0, 1, None): "3e587070ed2172101a2f1021c46aaa7d4afea9a50d7abf8a8a36dbae00acf0f8",
    ("indoor", 7, 3, None): "2efea91efd28eee3784806a7028bd1bd3b0e27cb58d175f2780435488461731b",
    ("indoor", 123456, 1, None): "e61402e9277d5de3b2f03aaeb0ae2a518bc9be236f0f5d6877aabf67eb25cb13",
    ("indoor", 5, 2, "small"): "404aeae57b42487bec3c4483e7ccf8194bfab571c40ffaeffdbbe7e2d8d21bf2",
    ("outdoor", 0, 1, None): "fe1dfe4900c0507b450ac16d0c34d2be305d4799643d074679941f768dec3c8a",
    ("outdoor", 7, 3, None): "400a7c2e84e461eb4c891e8e10686679ab6e328ab8b95c7eb0553e41555743cb",
    ("outdoor", 123456, 1, None): "6d1cdb847806e1cc596d86ad7b5ae965e581f21e591c1a14dccbadf3ccc2422c",
    ("outdoor", 5, 2, "small"): "f1166c2a3c656f147bfda508a844fef6f7668b53cb9732247d64b5002737b4ed",
}
ROOM_MESHES = {   # MeshData.digest() of the room parts of the default indoor scenes above
    (0, "room_floor"): "6697fff189c5cc86e1d784622001b635866aea7dd8b6536e7afab1dfeea9d659",
    (0, "room_walls"): "643e8a1569a2081e1e796f70dd6642ce5be11af07cbb21cb5968f5e6c324ab4d",
    (0, "room_ceiling"): "ed118269c85a4ef6abc700c3afdd9d3e244876f81c8819c4caecd022ef1ebd59",
    (7, "room_floor"): "a3cd9258a8236a04e9fafbfbb27e60b8d8e0e4ab55f0aa378abddc25e13fddb2",
    (7, "room_walls"): "26da3d833e0f2ccb240b3a88c16448b61920e14e0d187107d167813842c6ca61",
    (7, "room_ceiling"): "e6d0fa897d87a32fa692893246dea600fa8ddf70d2a2cbdd2012653cada8b51c",
    (123456, "room_floor"): "5558119f61bc63d130652f8647108a6ff9be8451d3fa8cd98e20e94d301cd5d0",
    (123456, "room_walls"): "19278f7fd3e7fa36517de46f94ad0169ed62c5ce3a0cad88bb37a0c171bad75f",
    (123456, "room_ceiling"): "d7f5057b877d85b769247974a91ad0b0898274c79d5e1b1b5c7f0a7cc9d6bf88",
}


def _spec(kind, seed, frames, config):
    cfg = SceneGenConfig.from_dict(SMALL) if config == "small" else None
    return sample_scene(seed, kind, num_frames=frames, config=cfg)


def _sha(spec) -> str:
    return hashlib.sha256(spec.to_json().encode()).hexdigest()


@pytest.mark.parametrize("key", list(SCENES), ids=lambda k: "-".join(map(str, k)))
def test_scene_specs_keep_their_bytes(key):
    assert _sha(_spec(*key)) == SCENES[key]


@pytest.mark.parametrize("seed", sorted({s for s, _ in ROOM_MESHES}))
def test_room_meshes_keep_their_bytes(seed):
    rooms = {o.name: meshes.build(o.mesh).digest() for o in _spec("indoor", seed, 1, None).objects
             if o.mesh.kind == "room"}
    assert rooms == {name: h for (s, name), h in ROOM_MESHES.items() if s == seed}


if __name__ == "__main__":
    for key in SCENES:
        print(key, _sha(_spec(*key)))
    for seed in sorted({s for s, _ in ROOM_MESHES}):
        for o in _spec("indoor", seed, 1, None).objects:
            if o.mesh.kind == "room":
                print((seed, o.name), meshes.build(o.mesh).digest())
