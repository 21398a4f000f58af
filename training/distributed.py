"""Data-parallel training across processes (``torchrun``), chosen from the environment in one place.

``torchrun --nproc_per_node N -m training train ...`` starts N processes with ``RANK``, ``WORLD_SIZE``
and ``LOCAL_RANK`` set; :func:`session` turns them into a process group (gloo for ``--device cpu``,
nccl for ``cuda``, each rank on ``cuda:LOCAL_RANK``) and :class:`Dist` tells the training loop which
rank it is. Without those variables (a plain ``python -m training train``), or with ``WORLD_SIZE=1``,
nothing is initialised and the loop runs exactly as a single process.

What each rank does (see :mod:`training.loop`): ``--batch`` is the **global** batch, split evenly
over the ranks (it must divide by ``WORLD_SIZE``). Step k's global batch is the one a single process
would draw (``training.data.EpochBatches``: items in an order fixed by (seed, epoch), crops and
augmentation a function of (seed, epoch, frame)); rank r takes its r-th contiguous share, so the
union of the ranks' crops in a step is exactly the one-process batch and results do not depend on N
beyond float rounding. DistributedDataParallel averages the gradients, so with losses that are means
over the batch the step equals the one-process step on the whole batch.
"""
from __future__ import annotations

import atexit
import os
import sys
from contextlib import contextmanager
from dataclasses import dataclass

import torch

from .errors import ConfigError

ENV = ("RANK", "WORLD_SIZE", "LOCAL_RANK")


@dataclass(frozen=True)
class Dist:
    """This process's place among the training processes (``world`` 1: a single process)."""

    rank: int = 0
    world: int = 1
    local_rank: int = 0

    @property
    def enabled(self) -> bool:
        return self.world > 1

    @property
    def is_main(self) -> bool:
        """Rank 0: the one that writes checkpoint.pt, metrics.csv and the progress bar."""
        return self.rank == 0

    def share(self, items: list) -> list:
        """This rank's contiguous share of one step's global batch ``items`` (len divisible by world)."""
        n = len(items) // self.world
        return items[self.rank * n:(self.rank + 1) * n]

    def mean(self, value: torch.Tensor) -> torch.Tensor:
        """The mean of a scalar tensor over the ranks (itself when single)."""
        if not self.enabled:
            return value
        v = value.detach().clone().reshape(1).float()
        torch.distributed.all_reduce(v)
        return v[0] / self.world

    def gather(self, obj) -> list:
        """Every rank's ``obj`` (picklable), in rank order ([obj] when single)."""
        if not self.enabled:
            return [obj]
        out = [None] * self.world
        torch.distributed.all_gather_object(out, obj)
        return out

    def barrier(self) -> None:
        if self.enabled:
            torch.distributed.barrier()


SINGLE = Dist()


def from_env(env=None) -> Dist:
    """The :class:`Dist` torchrun's variables describe (``SINGLE`` without them). Settings are checked:
    a partial or inconsistent set names the variable."""
    env = os.environ if env is None else env
    if "WORLD_SIZE" not in env:
        return SINGLE
    try:
        vals = {k: int(env.get(k, "0")) for k in ENV}
    except ValueError:
        raise ConfigError(f"torchrun's {', '.join(ENV)} must be integers, got "
                          f"{ {k: env.get(k) for k in ENV} }") from None
    rank, world, local = vals["RANK"], vals["WORLD_SIZE"], vals["LOCAL_RANK"]
    if world < 1 or not 0 <= rank < world or local < 0:
        raise ConfigError(f'"RANK" must be in 0..WORLD_SIZE-1 and "WORLD_SIZE" >= 1, got RANK={rank}, '
                          f"WORLD_SIZE={world}, LOCAL_RANK={local}")
    return Dist(rank, world, local)


def rank_device(name: str, dist: Dist) -> str:
    """The device name a rank trains on: ``cuda`` becomes ``cuda:LOCAL_RANK`` under torchrun (one GPU a
    process); an explicit ``cuda:N`` with several ranks is refused, it would put them all on one GPU."""
    if not dist.enabled or not name.startswith("cuda"):
        return name
    if name != "cuda":
        raise ConfigError(f'"device" is {name!r} under torchrun with {dist.world} ranks; pass --device cuda '
                          "and each rank uses cuda:LOCAL_RANK (CUDA_VISIBLE_DEVICES chooses the GPUs)")
    return f"cuda:{dist.local_rank}"


def backend_for(device: str) -> str:
    """nccl for CUDA ranks, gloo for CPU ones."""
    return "nccl" if device.startswith("cuda") else "gloo"


@contextmanager
def session(device: str = "cpu"):
    """Yield ``(Dist, device name)`` for this process. Under torchrun (``WORLD_SIZE`` > 1) it
    initialises the default process group from the environment (``env://``) unless one exists;
    otherwise it yields :data:`SINGLE` and ``device`` unchanged.

    The group it makes lives until the process exits (destroyed then, ``atexit``), so a process that
    trains several times (a script calling ``train`` in turn) reuses it: destroying and re-creating
    the default group under one torchrun rendezvous meets the first group's keys in torchrun's store,
    and it hung here (1 launch in 2)."""
    import torch.distributed as td
    if td.is_available() and td.is_initialized():
        dist = Dist(td.get_rank(), td.get_world_size(), from_env().local_rank)
        try:
            yield dist, rank_device(device, dist)
        except BaseException:
            _FAILED.append(True)
            raise
        return
    dist = from_env()
    if not dist.enabled:
        yield SINGLE, device
        return
    if not td.is_available():
        raise ConfigError("torch.distributed is not available in this build of PyTorch; run one process")
    dev = rank_device(device, dist)
    if dev.startswith("cuda"):
        if not torch.cuda.is_available() or dist.local_rank >= torch.cuda.device_count():
            raise ConfigError(f"rank {dist.rank} wants {dev} but this machine has "
                              f"{torch.cuda.device_count()} CUDA devices; start at most that many ranks a node")
        torch.cuda.set_device(dev)
    kw = {"device_id": torch.device(dev)} if dev.startswith("cuda") else {}
    td.init_process_group(backend_for(dev), **kw)
    atexit.register(_destroy)
    try:
        yield dist, dev
    except BaseException:
        _FAILED.append(True)
        raise


_FAILED = []


EXIT_BARRIER_S = 60.0     # how long a rank waits at exit for the others before it leaves without them


def _destroy() -> None:
    """At exit: meet the other ranks, then destroy the group, unless a rank's training raised (its peers
    may still wait in a collective, and a destroy could then block; torchrun stops them when this
    process exits).

    The meeting matters: a rank that destroyed its gloo group while its peer was still tearing down
    its own aborted with "terminate called without an active exception" (SIGABRT) after a finished
    run, so torchrun reported a failure: 9 of 40 two-rank CPU runs here, 0 of 80 with the barrier
    first. A peer that never arrives (killed) ends the wait after :data:`EXIT_BARRIER_S` and this
    rank leaves without destroying."""
    import datetime

    import torch.distributed as td
    if not td.is_initialized() or _FAILED:
        return
    try:
        if td.get_backend() == "gloo":
            td.monitored_barrier(timeout=datetime.timedelta(seconds=EXIT_BARRIER_S), wait_all_ranks=True)
        else:
            td.barrier(device_ids=[torch.cuda.current_device()])
    except RuntimeError as e:
        print(f"rank {td.get_rank()}: the other ranks did not reach the end of training ({e}); "
              "leaving without them", file=sys.stderr, flush=True)
        return
    td.destroy_process_group()


def end_process(code: int):
    """End this process with exit status ``code`` (a command's ``__main__`` calls it in place of
    ``sys.exit``). In a torchrun rank whose group is alive it meets the other ranks and destroys the
    group (:func:`_destroy`), flushes the standard streams and logging, and ends with ``os._exit``,
    skipping the interpreter's finalisation and C++'s static destructors.

    Why: after a finished run, with the group destroyed, gloo's threads (``gloo_tcp_loop``,
    ``pt_gloo_runloop``) were still alive here (the backend outlives ``destroy_process_group``
    while C++ holds it), and a rank rarely died in its exit with "terminate called without an
    active exception" (SIGABRT), so torchrun failed a run whose results were written: 9 of 40
    two-rank runs without the exit meeting, 0 of 80 with it, yet once more in a full test run.
    Nothing is left to finish at that point: outputs are written and closed by the commands, and
    zarr's and logging's exit work is only cleanup. Outside torchrun this is ``sys.exit(code)``."""
    import logging

    import torch.distributed as td
    if not (td.is_available() and td.is_initialized()):
        sys.exit(code)
    if not isinstance(code, int):         # sys.exit's rule: None is 0, anything else is printed and 1
        if code is not None:
            print(code, file=sys.stderr)
        code = 0 if code is None else 1
    _destroy()
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):     # a closed or broken pipe: nothing more can be said
            pass
    os._exit(code)


def wrap(model: torch.nn.Module, dist: Dist, device) -> torch.nn.Module:
    """``model`` in DistributedDataParallel when ``dist`` has several ranks (else itself).
    ``static_graph``: the set of parameters a model uses is fixed by its settings (a temporal model
    without a sampler, a one-layer partition), so DDP learns it on the first step, and modules that
    leave some parameters unused (or call submodules several times, as the recurrent models do over
    a window) work without ``find_unused_parameters``' per-step graph search."""
    if not dist.enabled:
        return model
    from torch.nn.parallel import DistributedDataParallel as DDP
    dev = torch.device(device)
    ids = [dev] if dev.type == "cuda" else None
    return DDP(model, device_ids=ids, static_graph=True)

