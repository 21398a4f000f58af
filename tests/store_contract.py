"""The contract every training store passes (``stores.protocol.TrainingStore``): our Zarr stores and
folders of Noisebase sequences alike, as zarr-python's ``StoreTests`` are for its stores. A test module
subclasses :class:`StoreContract` and gives the ``contract_store`` fixture (a finished store with at
least two clips, one of several frames)."""
from __future__ import annotations

import numpy as np
import pytest

from stores.contract import FEATURE_GROUPS, NUM_FEATURES
from stores.errors import CropSizeError, SampleCountError
from stores.protocol import DTYPES, TrainingStore

IMAGES = {"reference/radiance": 3, "reference/stderr": 3, "guides/albedo": 3, "guides/normal": 3,
          "guides/motion": 2}
COLUMNS = ("clip_id", "frame", "num_frames", "has_motion", "has_defocus", "scene_json", "case", "kind")


def check_dtypes(st) -> None:
    """Every array the store has comes back in a dtype the protocol allows (``stores.protocol.DTYPES``)."""
    i = st.complete_frames()[-1]
    for path, allowed in DTYPES.items():
        if st.has_array(path):
            a = st.read_array(path, i)
            assert a.dtype in allowed, f"{path}: {a.dtype}, the protocol allows {[np.dtype(d).name for d in allowed]}"


class StoreContract:
    """What training, evaluation and the fitness screen rely on (``stores/protocol.py``)."""

    def test_is_a_training_store(self, contract_store):
        st = contract_store
        assert isinstance(st, TrainingStore)
        assert st.num_frames == st.layout.num_frames >= 2 and isinstance(st.config, dict)
        assert set(st.missing_features) <= set(FEATURE_GROUPS)

    def test_splits_partition_the_complete_frames_by_clip(self, contract_store):
        st = contract_store
        done = st.complete_frames()
        assert st.incomplete_frames() == [] and done == list(range(st.num_frames))
        assert sorted(st.frames_in_split(None)) == done
        parts = [st.frames_in_split(s) for s in st.split_fractions]
        assert sorted(i for p in parts for i in p) == done                     # every frame, once
        for s, frames in zip(st.split_fractions, parts):
            assert all(st.split_of_frame(i) == s for i in frames)
            assert sorted(i for c in st.clips(s).values() for i in c) == sorted(frames)
        with pytest.raises(ValueError):
            st.frames_in_split("no-such-split")

    def test_clips_are_whole_and_in_clip_order(self, contract_store):
        st = contract_store
        clips = st.clips(None)
        clip_id, in_clip = st.meta_column("clip_id"), st.meta_column("frame")
        assert len(clips) >= 2 and any(len(c) > 1 for c in clips.values())
        for cid, frames in clips.items():
            assert [int(in_clip[i]) for i in frames] == list(range(len(frames)))
            assert all(int(clip_id[i]) == cid for i in frames)
            assert len({st.split_of_frame(i) for i in frames}) == 1             # a clip never straddles splits

    def test_columns(self, contract_store):
        st = contract_store
        for key in COLUMNS:
            assert len(st.meta_column(key)) == st.num_frames, key
        assert (st.meta_column("num_frames")[st.frames_in_split(None)] >= 1).all()
        from stores.protocol import scene_kinds
        assert len(scene_kinds(st)) == st.num_frames and all(isinstance(k, str) for k in scene_kinds(st))
        with pytest.raises(KeyError):
            st.meta_column("no-such-column")

    def test_arrays_in_the_training_layout(self, contract_store):
        st = contract_store
        S, (H, W) = st.layout.spp, (st.layout.height, st.layout.width)
        crop, i = (1, 2, H - 3, W - 4), st.num_frames - 1
        h, w = crop[2:]
        assert st.has_array("inputs/radiance") and st.has_array("inputs/features")
        assert not st.has_array("no/such-array")
        rad = st.read_array("inputs/radiance", i, crop, samples=S - 1)
        feat = st.read_array("inputs/features", i, crop)
        assert rad.shape == (S - 1, 3, h, w) and feat.shape == (S, NUM_FEATURES, h, w)
        assert rad.dtype == np.float32 and np.isfinite(rad).all() and (rad >= 0).all()
        for g in st.missing_features:
            assert not feat[:, FEATURE_GROUPS[g]].any(), g
        for path, c in IMAGES.items():
            a = st.read_array(path, i, crop)
            assert a.shape == (c, h, w) and a.dtype == np.float32, path
        assert st.read_array("guides/depth", i, crop).shape == (h, w)
        full = st.read_array("inputs/radiance", i)
        np.testing.assert_array_equal(full[:S - 1, :, 1:1 + h, 2:2 + w], rad)      # a crop is the window
        with pytest.raises(CropSizeError):
            st.read_array("inputs/radiance", i, (0, 0, H + 1, W))
        with pytest.raises(SampleCountError):
            st.read_array("inputs/radiance", i, samples=S + 1)
        with pytest.raises(IndexError):
            st.read_array("inputs/radiance", st.num_frames)

    def test_every_array_in_its_dtype(self, contract_store):
        check_dtypes(contract_store)

    def test_a_finished_store_is_fit(self, contract_store):
        st = contract_store
        assert st.check_frames(st.complete_frames()) == {}
