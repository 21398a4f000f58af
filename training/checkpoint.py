"""Checkpoints that resume exactly and are safe to share: model and optimiser state, RNG states, step,
the training config, the model's config and the store's schema version (and path).

Everything in a checkpoint is plain data (dicts, lists, tuples, str, int, float, bool, None and
tensors), so :func:`load` reads it with ``torch.load(..., weights_only=True)``: opening a file someone
shared never runs code it carries. :func:`save` refuses to write anything else, naming the field. A
file that would need pickle (a ``/1`` checkpoint of an older version of this project, or a crafted
one) is refused with a :class:`CheckpointError` that names it and the objects it asks for; one you
made yourself converts once with ``python -m training.checkpoint upgrade FILE``, which reads it with
the same restricted unpickler, allowing only the few objects old checkpoints of this project hold
(:data:`OLD_GLOBALS`: numpy arrays of the RNG state, torch's version string); a file that asks for
anything else (``os.system``, ``subprocess.Popen``, ``builtins.eval``, ...) is refused, naming it, and
nothing in it runs. ``load`` recommends ``upgrade`` only for a file that asks for those objects alone.
``load`` also refuses a mismatch with a named error.
"""
from __future__ import annotations

import pickle
import random
from collections import OrderedDict
from pathlib import Path

import numpy as np
import torch

from .config import TrainConfig
from .errors import CheckpointError

FORMAT = "denoise-datagen.training-checkpoint/2"   # /2: plain data only (weights_only); /1 needed pickle
OLD_FORMATS = ("denoise-datagen.training-checkpoint/1",)
PLAIN_TYPES = (type(None), bool, int, float, str, torch.Tensor)
PLAIN_DATA = "dicts, lists, tuples, str, int, float, bool, None and tensors"


def _numpy_state(state: tuple) -> dict:
    """``np.random.get_state()`` as plain data."""
    name, keys, pos, has_gauss, gauss = state
    return {"bit_generator": str(name), "key": torch.from_numpy(np.asarray(keys, np.int64)), "pos": int(pos),
            "has_gauss": int(has_gauss), "cached_gaussian": float(gauss)}


def _python_state(state: tuple) -> dict:
    """``random.getstate()`` as plain data."""
    version, internal, gauss_next = state
    return {"version": int(version), "state": list(internal), "gauss_next": gauss_next}


def rng_state() -> dict:
    """The torch, numpy and Python RNG states (and CUDA's) as plain data."""
    state = {"torch": torch.get_rng_state(), "numpy": _numpy_state(np.random.get_state()),
             "python": _python_state(random.getstate())}
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict) -> None:
    """Restore what :func:`rng_state` returned (after a save and load)."""
    torch.set_rng_state(state["torch"])
    n = state["numpy"]
    np.random.set_state((n["bit_generator"], n["key"].numpy().astype(np.uint32), n["pos"], n["has_gauss"],
                         n["cached_gaussian"]))
    p = state["python"]
    random.setstate((p["version"], tuple(p["state"]), p["gauss_next"]))
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def check_plain(obj, where: str = "checkpoint") -> None:
    """Raise :class:`CheckpointError` naming the first field of ``obj`` that is not plain data
    (``PLAIN_DATA``), which ``torch.load(..., weights_only=True)`` could not read back."""
    if type(obj) in (dict, OrderedDict):         # subclasses would need pickle
        for k, v in obj.items():
            if not isinstance(k, (str, int)) or isinstance(k, bool):
                raise CheckpointError(f"{where} has a key {k!r} of type {type(k).__name__}; keys must be str or int")
            check_plain(v, f"{where}.{k}")
    elif type(obj) in (list, tuple, torch.Size):
        for i, v in enumerate(obj):
            check_plain(v, f"{where}[{i}]")
    elif type(obj) not in PLAIN_TYPES and not isinstance(obj, torch.Tensor):
        raise CheckpointError(f"{where} is a {type(obj).__module__}.{type(obj).__qualname__}; a checkpoint "
                              f"holds only plain data ({PLAIN_DATA}) so it loads without pickle")


def _write(path: Path, payload: dict) -> None:
    """``torch.save`` to a temp file, then rename: an interrupted save never leaves a broken file."""
    from core.files import write_atomically
    write_atomically(path, lambda f: torch.save(payload, f), binary=True)


def save(path, *, model, optimizer, step: int, cfg: TrainConfig, store_info: dict, extra: dict | None = None) -> None:
    """Write atomically (:func:`_write`). Every field must be plain data (:func:`check_plain`)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    payload = {
        "format": FORMAT, "model": cfg.model, "model_config": dict(model.config), "train_config": cfg.to_dict(),
        "state_dict": model.state_dict(), "optimizer": optimizer.state_dict() if optimizer else None,
        "step": int(step), "rng": rng_state(), "store": dict(store_info), "torch_version": str(torch.__version__),
        **(extra or {}),
    }
    check_plain(payload)
    _write(path, payload)


SAFE_TORCH = (2, 6)     # torch.load(weights_only=True) can be made to run code before 2.6 (CVE-2025-32434)


def _require_safe_torch() -> None:
    """Refuse to unpickle anything with a torch whose restricted unpickler can be bypassed."""
    from torch.torch_version import TorchVersion
    if TorchVersion(torch.__version__) < SAFE_TORCH:
        raise CheckpointError(f"torch {torch.__version__} is too old to read checkpoints safely: its weights_only "
                              "loader can be bypassed (CVE-2025-32434); install torch >= 2.6")


def _old_globals() -> list:
    """What a ``/1`` checkpoint of this project needs beyond plain data, for torch's restricted
    unpickler (``torch.serialization.safe_globals``): the numpy RNG state's array (``ndarray``, its
    ``dtype`` and ``_reconstruct``, under numpy 1's module name ``numpy.core`` as well as numpy 2's
    ``numpy._core``) and torch's ``TorchVersion`` string. Nothing here runs code of the file's choosing:
    each rebuilds a value from data."""
    try:
        from numpy._core import multiarray as ma
    except ImportError:           # numpy 1
        from numpy.core import multiarray as ma
    from torch.torch_version import TorchVersion
    out = [TorchVersion, np.ndarray, np.dtype, ma._reconstruct,
           (ma._reconstruct, "numpy.core.multiarray._reconstruct"),
           (ma._reconstruct, "numpy._core.multiarray._reconstruct")]
    dtypes = getattr(np, "dtypes", None)             # numpy 2 pickles a dtype through its class
    if dtypes is not None:
        out += [getattr(dtypes, n) for n in dir(dtypes) if n.endswith("DType")]
    return out


OLD_GLOBAL_NAMES = ("torch.torch_version.TorchVersion", "numpy.ndarray", "numpy.dtype",
                    "numpy.core.multiarray._reconstruct", "numpy._core.multiarray._reconstruct")


def _is_old_global(name: str) -> bool:
    """Whether ``name`` is one of the objects a ``/1`` checkpoint of this project holds."""
    return name in OLD_GLOBAL_NAMES or (name.startswith("numpy.dtypes.") and name.endswith("DType"))


def _unsafe_globals(path: Path) -> list[str]:
    """The Python objects a checkpoint file asks pickle for, read without running any of them
    (empty when torch cannot list them, e.g. for a bare pickle file)."""
    try:
        return list(torch.serialization.get_unsafe_globals_in_checkpoint(path))
    except Exception:   # noqa: BLE001 - not a zip checkpoint, or an older torch: the message says less
        return []


def _unpickler_reason(e: Exception) -> str:
    """The part of torch's long weights-only refusal that says what it met (``Unsupported global: GLOBAL
    numpy...``, ``Unsupported operand 110``)."""
    text = str(e)
    if "WeightsUnpickler error:" in text:
        text = text.split("WeightsUnpickler error:", 1)[1].split("Check the documentation", 1)[0]
    return " ".join(text.split()) or type(e).__name__


def _refusal(path: Path, e: Exception) -> CheckpointError:
    """Why ``path`` was refused by torch's restricted unpickler, in our words (torch's own message goes on
    to suggest the unsafe way round it, which is never repeated here): damaged or foreign, not a
    checkpoint this project wrote, or an old-format one of ours with the command that converts it."""
    import re
    import zipfile
    why = _unpickler_reason(e)
    named = re.findall(r"GLOBAL ([\w.]+)", why)
    if not named:                                 # no object asked for: a damaged or foreign file
        return CheckpointError(f"cannot read checkpoint {path}: {why.split('. ')[0]}")
    needs = _unsafe_globals(path) or named
    foreign = [n for n in needs if not _is_old_global(n)]
    ours = zipfile.is_zipfile(path)               # torch.save's format: every checkpoint this project wrote
    if foreign or not ours:
        return CheckpointError(
            f"refusing to load {path}: it is not a checkpoint this project wrote"
            + ("" if ours else " (a bare pickle, not torch's checkpoint format)")
            + f": it asks pickle for {', '.join(needs)} (a checkpoint holds only {PLAIN_DATA}), and unpickling "
            "it could run code the file carries. Nothing in it was run. Do not load it: ask its author for a "
            "checkpoint of this project, or retrain."
            + ("" if foreign else " (A checkpoint an older version of this project wrote is a torch zip file: "
               "python -m training.checkpoint upgrade FILE converts one.)"))
    return CheckpointError(
        f"refusing to load {path}: it is an old-format checkpoint that needs the Python objects {needs} (a "
        f"checkpoint now holds only {PLAIN_DATA}). Convert it once: python -m training.checkpoint upgrade "
        f"{path} (it reads the file without running any code and refuses anything but those objects).")


def load(path, map_location="cpu") -> dict:
    """Read a checkpoint with ``torch.load(..., weights_only=True)``: only plain data is accepted, so
    nothing in the file runs. Raises :class:`CheckpointError` for a missing, corrupt, pickle-needing or
    foreign file."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"no checkpoint at {path}")
    _require_safe_torch()
    try:
        ck = torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as e:
        raise _refusal(path, e) from e
    except Exception as e:   # torch raises many types for a corrupt file
        raise CheckpointError(f"cannot read checkpoint {path}: {e}") from e
    if not isinstance(ck, dict) or ck.get("format") != FORMAT:
        fmt = ck.get("format") if isinstance(ck, dict) else type(ck).__name__
        raise CheckpointError(f"{path} is not a {FORMAT} checkpoint (format: {fmt!r})")
    return ck


def _load_old(path: Path) -> dict:
    """A checkpoint of any format of this project, read by torch's restricted (``weights_only``)
    unpickler with only :func:`_old_globals` allowed besides plain data: nothing the file carries runs.
    Anything else it asks for is a :class:`CheckpointError` naming it."""
    _require_safe_torch()
    try:
        with torch.serialization.safe_globals(_old_globals()):
            return torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as e:
        needs = [n for n in _unsafe_globals(path) if not _is_old_global(n)]
        what = ", ".join(needs) if needs else _unpickler_reason(e)
        raise CheckpointError(
            f"refusing to upgrade {path}: it asks for {what}, which no checkpoint of this project holds "
            f"(old checkpoints need only {', '.join(OLD_GLOBAL_NAMES[:3])} and numpy's array rebuild); "
            "nothing in it was run and nothing was written") from e
    except Exception as e:   # noqa: BLE001 - torch raises many types for a corrupt file
        raise CheckpointError(f"cannot read checkpoint {path}: {e}") from e


def upgrade(path, out=None) -> Path:
    """Rewrite a ``/1`` checkpoint (numpy RNG arrays, torch's version string) as a ``/2`` plain-data one,
    at ``out`` (default: in place). The file is read by torch's restricted unpickler (:func:`_load_old`):
    it may ask for the few objects old checkpoints hold and nothing else, so a crafted file is refused
    (naming what it asks for) before anything in it runs."""
    path = Path(path)
    out = Path(out) if out is not None else path
    if not path.is_file():
        raise CheckpointError(f"no checkpoint at {path}")
    ck = _load_old(path)
    if not isinstance(ck, dict) or ck.get("format") not in OLD_FORMATS + (FORMAT,):
        raise CheckpointError(f"{path} is not a training checkpoint of this project; nothing written")
    if ck["format"] in OLD_FORMATS:
        ck["rng"]["numpy"] = _numpy_state(ck["rng"]["numpy"])
        ck["rng"]["python"] = _python_state(ck["rng"]["python"])
        ck["torch_version"] = str(ck.get("torch_version", ""))
        ck["model_config"] = dict(ck["model_config"])
        ck["format"] = FORMAT
    check_plain(ck, str(path))
    _write(out, ck)
    return out


def build_model(ck: dict, device="cpu"):
    """The checkpoint's model with its weights, in eval mode. A setting the checkpoint does not record (it
    was written before the setting existed, such as ``outliers``, training.models.robust) takes the value the
    model was trained with (the model's ``legacy_config``), not today's default."""
    from .models import build, get
    model = build(ck["model"], **{**get(ck["model"]).legacy_config, **ck["model_config"]})
    model.load_state_dict(ck["state_dict"])
    return model.to(device).eval()


def find_runs(runs) -> list[Path]:
    """Run directories holding a ``checkpoint.pt`` (a run folder or its checkpoint file; globs that matched
    nothing are skipped)."""
    found = []
    for r in runs:
        p = Path(r)
        if (p / "checkpoint.pt").is_file():
            found.append(p)
        elif p.is_file() and p.suffix == ".pt":
            found.append(p.parent)
    return found


def _parser(argv: list[str]):
    from core.cli import commands, program_parser
    ap = program_parser("python -m training.checkpoint",
                        "Convert an old checkpoint of this project to the plain-data format.")
    u = commands(ap, dest="cmd").add_parser(
        "upgrade", help="rewrite an old /1 checkpoint as /2 (read by a restricted unpickler: only the numpy "
                        "arrays and version string old checkpoints hold are allowed)")
    u.add_argument("file")
    u.add_argument("--out", help="where to write it (default: replace FILE)")
    u.set_defaults(run=lambda a: print(f"wrote {upgrade(a.file, a.out)} ({FORMAT})"))
    return ap


def main(argv=None) -> int:
    """``python -m training.checkpoint upgrade FILE [--out NEW]``: convert a trusted old checkpoint."""
    from core.cli import Program, run_main
    return run_main(Program(parser=_parser), argv)


if __name__ == "__main__":  # pragma: no cover
    from core.cli import start
    start(main)
