"""The dataset's Dask graph: scenes → per-frame renders (inputs, layers, reference) → store writes.

:func:`build_graph` returns a :class:`DatasetGraph`, plain data: one :class:`Node` per task with a
readable key, its function, its arguments (:class:`Ref` to other nodes) and its worker resources.
:meth:`DatasetGraph.submit` hands it to a ``distributed.Client`` with ``client.submit(key=...,
resources=..., retries=...)`` node by node, so keys, resources and retries reach the scheduler exactly
as built (no graph optimisation can drop an annotation or fuse keys away).

Keys (stage first, because the dashboard's progress pane groups tasks by the key's prefix)::

    spec-scene-000042@T                     scene_gen.sampling.sample_scene → SceneSpec JSON (stored once a clip)
    inputs-scene-000042/frame-3@T           per-sample inputs + guides       (split)
    layers-scene-000042/frame-3@T           sample layers                    (split)
    reference-scene-000042/frame-3@T        reference (+ resources, e.g. GPU) (split)
    render-scene-000042/frame-3@T           the whole frame                  (not split: the default)
    write-scene-000042/frame-3@T            gathers the parts, writes the frame's image shards, returns its
                                            record (with the scene's clip id, ``FrameRef.clip_id``), which
                                            the client commits (``stores.writer``: metadata, status last)

``T`` is a short token of (dataset content, store path), so two datasets on one shared scheduler never
share a key. Store writes (schema v3, ``stores.writer``): one task per frame gathers its parts and writes
the frame's image shards only (``pipeline.tasks.write_frame``) and returns its record; the client commits
finished frames' records together (``frames/*``, then ``status/error``, then ``status/complete`` last;
``pipeline.dataset.Committer``), so no task writes a shared metadata chunk. At most one frame's parts
wait in memory per write, and write tasks have a higher priority than renders so finished frames leave
memory first. Validation and the summary run after the writes (``pipeline.dataset``) because frames
that keep failing are recorded in the store first.
"""
from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from types import SimpleNamespace
from typing import Any, Callable, Iterable

from pipeline import tasks as _tasks
from pipeline.config import DatasetConfig, FrameRef

WRITE_PRIORITY = 10      # writes before renders: finished frames leave worker memory first


def default_functions() -> SimpleNamespace:
    """The task functions the graph calls (tests may pass others with the same signatures)."""
    return SimpleNamespace(make_spec=_tasks.make_spec, render_inputs=_tasks.render_inputs,
                           render_layers=_tasks.render_layers, render_reference=_tasks.render_reference,
                           render_whole_frame=_tasks.render_whole_frame, write_frame=_tasks.write_frame)


@dataclass(frozen=True)
class Ref:
    """An argument that is the result of another node."""
    key: str


@dataclass(frozen=True)
class Node:
    key: str
    func: Callable
    args: tuple
    stage: str
    resources: dict | None = None
    priority: int = 0
    frame_index: int | None = None
    kwargs: dict | None = None          # literal keyword arguments (the write's clip id)

    @property
    def dependencies(self) -> tuple[str, ...]:
        return tuple(a.key for a in self.args if isinstance(a, Ref))


@dataclass
class DatasetGraph:
    """Nodes in topological order, plus which write node finishes which store frame."""
    nodes: dict[str, Node] = field(default_factory=dict)
    writes: dict[int, str] = field(default_factory=dict)     # store frame index -> write key
    retries: int = 0
    token: str = ""

    def add(self, node: Node) -> str:
        if node.key in self.nodes:
            raise ValueError(f"duplicate key {node.key!r}")
        missing = [d for d in node.dependencies if d not in self.nodes]
        if missing:
            raise ValueError(f"{node.key!r} depends on unknown keys {missing}")
        self.nodes[node.key] = node
        return node.key

    def stages(self) -> dict[str, int]:
        out: dict[str, int] = {}
        for n in self.nodes.values():
            out[n.stage] = out.get(n.stage, 0) + 1
        return out

    def submit(self, client) -> dict[str, Any]:
        """Submit every node to ``client``; returns key → Future (all of them, so none is released)."""
        futures: dict[str, Any] = {}
        for k, n in self.nodes.items():
            args = [futures[a.key] if isinstance(a, Ref) else a for a in n.args]
            futures[k] = client.submit(n.func, *args, **(n.kwargs or {}), key=k, pure=False, retries=self.retries,
                                       resources=n.resources, priority=n.priority)
        return futures


def graph_token(cfg: DatasetConfig, store: str) -> str:
    """8 hex digits identifying (dataset content, store path)."""
    text = json.dumps({"content": cfg.to_dict() | {"out": None, "cluster": None, "tasks": None}, "store": store},
                      sort_keys=True, default=str)
    return hashlib.sha1(text.encode()).hexdigest()[:8]


def frame_key(stage: str, ref: FrameRef, token: str) -> str:
    return f"{stage}-{ref.key}@{token}" if token else f"{stage}-{ref.key}"


def spec_key(scene: int, token: str) -> str:
    base = f"spec-scene-{scene:06d}"
    return f"{base}@{token}" if token else base


def build_graph(cfg: DatasetConfig, store: str, frames: Iterable[FrameRef] | None = None, *,
                functions: SimpleNamespace | None = None, token: str | None = None,
                generation: str = "") -> DatasetGraph:
    """The graph that renders and writes ``frames`` (default: all of ``cfg``'s) into ``store``.

    Scene specs are made once per scene that has a frame to render, and each stores its SceneSpec JSON
    at the scene's first frame (``pipeline.tasks.scene_spec``). ``functions`` replaces the task
    functions (same signatures as :func:`default_functions`'s). ``generation``
    (``stores.writer.generation``) lets each worker keep the store's writer open between frames.
    """
    fn = functions or default_functions()
    frames = list(cfg.frames() if frames is None else frames)
    token = graph_token(cfg, store) if token is None else token
    render = {**cfg.render, "res": list(cfg.resolution)}
    scene_gen = dict(cfg.scene_gen)
    ref_res = dict(cfg.tasks.reference_resources) if cfg.tasks.reference_resources else None
    g = DatasetGraph(retries=cfg.tasks.retries, token=token)
    for ref in sorted(frames, key=lambda r: r.index):
        sk = spec_key(ref.scene, token)
        if sk not in g.nodes:
            made_of = ref.source if ref.source is not None else scene_gen      # a scene file's, or the generator's
            g.add(Node(sk, _tasks.scene_spec, (store, ref.index - ref.frame, ref.seed, ref.kind, ref.num_frames,
                                               tuple(cfg.resolution), made_of)
                       + ((ref.case,) if ref.case else ()), "spec",           # a hard case (scene_gen.cases)
                       kwargs={"make": fn.make_spec, **({"generation": generation} if generation else {})}))
        spec = Ref(sk)
        if cfg.tasks.split:
            parts = (
                g.add(Node(frame_key("inputs", ref, token), fn.render_inputs, (spec, ref.frame, render), "inputs")),
                g.add(Node(frame_key("layers", ref, token), fn.render_layers, (spec, ref.frame, render), "layers")),
                g.add(Node(frame_key("reference", ref, token), fn.render_reference, (spec, ref.frame, render),
                           "reference", resources=ref_res)),
            )
        else:
            parts = (g.add(Node(frame_key("render", ref, token), fn.render_whole_frame, (spec, ref.frame, render),
                                "render")),)
        wk = g.add(Node(frame_key("write", ref, token), fn.write_frame,
                        (store, ref.index, spec, ref.frame, *map(Ref, parts)), "write",
                        priority=WRITE_PRIORITY, frame_index=ref.index,
                        kwargs={**({"clip_id": ref.clip_id} if ref.clip_id is not None else {}),
                                **({"generation": generation} if generation else {})} or None))
        g.writes[ref.index] = wk
    return g
