"""What a training store offers, written down once: :class:`TrainingStore`.

Two formats implement it: our Zarr stores (:class:`stores.reader.Store`) and folders of Noisebase
sequences (:class:`stores.noisebase.NoisebaseStore`); ``tests/store_contract.py`` is the one contract
suite both pass. Everything downstream of the store (``training``: datasets, input kinds, the fitness
screen, evaluation) reads through these members only, so a third format is one class that passes the
suite.

Layouts, as the datasets consume them (no transpose on read): ``read_array("inputs/radiance", i)``
float32 ``(S, 3, h, w)``, ``"inputs/features"`` ``(S, 17, h, w)`` float16 or float32 (as stored: the
features are float16 in our stores and go to the device so, to be widened there), images ``(C, h, w)``
(``reference/*``, ``guides/albedo|normal|motion``), ``"guides/depth"`` ``(h, w)``, ``"layers/radiance"``
``(L, 3, h, w)``, all float32; a crop is ``(y, x, h, w)``. :data:`DTYPES` says it for the contract suite.
"""
from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np

# array -> the dtypes read_array may return (the contract suite checks every array a store has)
DTYPES = {"inputs/radiance": (np.float32,), "inputs/features": (np.float16, np.float32),
          "layers/radiance": (np.float32,), "reference/radiance": (np.float32,),
          "reference/stderr": (np.float32,), "guides/albedo": (np.float32,), "guides/normal": (np.float32,),
          "guides/depth": (np.float32,), "guides/motion": (np.float32,)}


@runtime_checkable
class TrainingStore(Protocol):
    """A store that training, evaluation and the fitness screen read (module docstring)."""

    path: str                            # where it is (for messages and records)
    layout: object                       # stores.schema.StoreLayout: frames, H, W, spp, layer_spp
    missing_features: tuple[str, ...]    # feature groups it does not hold (read as 0; models reading them are refused)

    @property
    def num_frames(self) -> int: ...

    @property
    def schema_version(self) -> int | str: ...

    @property
    def config(self) -> dict: ...

    @property
    def split_fractions(self) -> dict: ...

    def has_array(self, path: str) -> bool:
        """Whether ``read_array(path, ...)`` can read it (``inputs/radiance``, ``layers/radiance``, ...)."""

    def read_array(self, path: str, i: int, crop=None, *, samples: int | None = None,
                   check_complete: bool = True) -> np.ndarray:
        """Frame ``i`` of array ``path`` in the layout above, of a dtype of :data:`DTYPES`, cropped, the
        first ``samples``."""

    def complete_frames(self) -> list[int]: ...

    def incomplete_frames(self) -> list[int]: ...

    def frames_in_split(self, split: str | None, *, complete_only: bool = True) -> list[int]: ...

    def clips(self, split: str | None = None, *, complete_only: bool = True) -> dict[int, list[int]]:
        """clip id -> its frames in clip order."""

    def split_of_frame(self, i: int) -> str: ...

    def meta_column(self, key: str) -> np.ndarray:
        """A per-frame column: ``clip_id``, ``frame`` (index in the clip), ``num_frames``, ``has_motion``,
        ``has_defocus``, ``scene_json``, ``case``, ``kind`` (the scene family; '' where unknown)."""

    def check_frames(self, frames, *, progress: bool = False) -> dict[int, list[str]]:
        """The frames of ``frames`` that are unfit to use, frame -> problems (``stores.fitness``)."""


def open_training_store(store) -> TrainingStore:
    """The one opener of every consumer (training's datasets and commands, the studies): the
    :class:`TrainingStore` at a path, or ``store`` itself when it is one: a :class:`stores.reader.Store`,
    or for a folder of Noisebase sequences a :class:`stores.noisebase.NoisebaseStore`, which every
    consumer reads alike. Raises the stores' own errors (``StoreError``, ``FileNotFoundError``)."""
    if isinstance(store, TrainingStore):
        return store
    from stores import noisebase
    from stores.reader import open_store
    return noisebase.NoisebaseStore(store) if noisebase.is_noisebase(store) else open_store(store)


def scene_kinds(store) -> np.ndarray:
    """Every frame's scene family (str, one a frame; '' where unknown) from ``frames/kind``; for a store
    made before that column, from each clip's scene JSON (:func:`_column_or_spec`)."""
    return _column_or_spec(store, "kind")


def scene_cases(store) -> np.ndarray:
    """Every frame's hard-case tag (str; '' for ordinary frames) from ``frames/case``; for the frames of
    a store made before that column, from each clip's scene JSON (:func:`_column_or_spec`). A frame whose
    ``frames/kind`` is filled was written by a pipeline that records its case (``kind`` came after
    ``case``), so its '' is an ordinary frame's, and no JSON is read for it."""
    recorded = np.array([str(k) != "" for k in store.meta_column("kind")], bool)
    return _column_or_spec(store, "case", recorded)


def _column_or_spec(store, key: str, recorded: np.ndarray | None = None) -> np.ndarray:
    """The ``frames/<key>`` column, and for the frames where it is '' (a store made before the column
    existed reads '' there, and so do the frames made before it of such a store resumed since) the
    ``key`` of the scene's JSON, parsed once for each distinct text (once a clip) and only where the text
    names the key: the one place a reader of the stores looks inside the generator's JSON. ``recorded``:
    the frames whose '' is a value, not a gap (never looked up)."""
    import json
    col = np.array([str(k) for k in store.meta_column(key)], dtype=object)
    missing = np.nonzero((col == "") & (True if recorded is None else ~recorded))[0]
    if len(missing) == 0:
        return col.astype(str)
    texts, done = store.meta_column("scene_json"), {}
    for i in missing:
        text = str(texts[i])                    # a clip's frames share their scene's text: parsed once
        if text not in done:
            done[text] = ""
            if f'"{key}"' in text:
                try:
                    d = json.loads(text)
                    done[text] = str(d.get(key, "")) if isinstance(d, dict) else ""
                except ValueError:                 # a synthetic store's placeholder
                    pass
        col[i] = done[text]
    return col.astype(str)

def scene_files(store) -> np.ndarray:
    """Every frame's scene file (str: the path its scene's JSON records as ``source.path``; '' for a
    generated scene), read only for the frames whose ``frames/kind`` is ``file``, and each clip's JSON
    parsed once."""
    import json
    kinds = scene_kinds(store)
    out = np.full(len(kinds), "", dtype=object)
    pick = np.nonzero(kinds == "file")[0]
    if len(pick) == 0:
        return out.astype(str)
    texts, done = store.meta_column("scene_json"), {}
    for i in pick:
        text = str(texts[i])
        if text not in done:
            try:
                d = json.loads(text) if '"source"' in text else {}
                done[text] = str((d.get("source") or {}).get("path", "")) if isinstance(d, dict) else ""
            except ValueError:
                done[text] = ""
        out[i] = done[text]
    return out.astype(str)


__all__ = ["TrainingStore", "open_training_store", "scene_kinds", "scene_cases", "scene_files"]
