"""training.checkpoint is safe to share: checkpoints hold plain data only and load with
``torch.load(..., weights_only=True)``; a file that would need pickle is refused before anything in it
runs, naming the file and the way forward; a trusted old (/1) checkpoint upgrades once."""
from __future__ import annotations

import os
import pickle
import random

import numpy as np
import pytest
import torch

from training import checkpoint as ckpt
from training.config import TrainConfig
from training.errors import CheckpointError
from training.models import build, names

TINY = dict(embed=8, context=8, kernel_size=5, partition_hidden=(8,), kernel_hidden=(8,),
            unet_encoder=((8,), (8,)), unet_bottleneck=(8,), unet_decoder=((8,), (8,)))
STORE = {"path": "/tmp/x.zarr", "schema_version": 3, "layout": {"height": 8, "layer_spp": [1, 2]},
         "config_sha256": "0" * 64}


class WritesMarker:
    """Unpickling this runs ``os.system('touch MARKER')``: what a malicious checkpoint would do."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return os.system, (f"touch {self.marker}",)


def _model_and_optimizer():
    torch.manual_seed(0)
    model = build("layer", **TINY)
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    model(_batch(model)).mean().backward()      # an optimiser state with moments and a step count
    opt.step()
    return model, opt


def _batch(model):
    from test_models import kind_batch
    return kind_batch(model)


def _save(path, **extra):
    model, opt = _model_and_optimizer()
    cfg = TrainConfig(model="layer", model_cfg=TINY, steps=4, batch=2, crop=16, spp=2)
    ckpt.save(path, model=model, optimizer=opt, step=7, cfg=cfg, store_info=STORE, extra=extra or None)
    return model, opt, cfg


def test_saved_checkpoint_is_plain_data_and_restores_everything(tmp_path):
    model, opt, cfg = _save(tmp_path / "c.pt")
    raw = torch.load(tmp_path / "c.pt", weights_only=True)       # torch's own safe loader reads it all
    assert raw["format"] == ckpt.FORMAT and raw["step"] == 7 and type(raw["torch_version"]) is str
    ck = ckpt.load(tmp_path / "c.pt")
    assert TrainConfig.from_dict(ck["train_config"]) == cfg      # tuples in the settings survive
    assert ck["store"] == STORE
    m2 = ckpt.build_model(ck)
    for k, v in model.state_dict().items():
        assert torch.equal(m2.state_dict()[k], v), k
    opt2 = torch.optim.Adam(m2.parameters(), lr=1e-3)
    opt2.load_state_dict(ck["optimizer"])
    s1, s2 = opt.state_dict()["state"], opt2.state_dict()["state"]
    assert torch.equal(s1[0]["exp_avg"], s2[0]["exp_avg"]) and float(s2[0]["step"]) == 1.0
    # the RNG states come back exactly: the same draws after restoring
    ckpt.set_rng_state(ck["rng"])
    a = (torch.rand(3), np.random.rand(3), random.random(), np.random.randn())
    ckpt.set_rng_state(ck["rng"])
    b = (torch.rand(3), np.random.rand(3), random.random(), np.random.randn())
    assert torch.equal(a[0], b[0]) and np.array_equal(a[1], b[1]) and a[2] == b[2] and a[3] == b[3]


@pytest.mark.parametrize("name", names())
def test_every_model_config_is_plain_data(name):
    from test_models import tiny_cfg
    ckpt.check_plain(dict(build(name, **tiny_cfg(name)).config), f"{name}.config")


def test_save_refuses_fields_that_would_need_pickle(tmp_path):
    with pytest.raises(CheckpointError, match=r"checkpoint\.note is a numpy\.float64"):
        _save(tmp_path / "c.pt", note=np.float64(1.0))
    with pytest.raises(CheckpointError, match=r"checkpoint\.bad\[1\] is a .*WritesMarker"):
        _save(tmp_path / "c.pt", bad=[1, WritesMarker(tmp_path / "m")])
    assert not (tmp_path / "c.pt").exists()


@pytest.mark.filterwarnings("ignore:Detected pickle protocol")
@pytest.mark.parametrize("writer", ["torch.save", "pickle-2", "pickle-4"])
def test_a_checkpoint_that_carries_code_is_refused_and_nothing_runs(tmp_path, writer):
    marker = tmp_path / "ran"
    path = tmp_path / "shared.pt"
    payload = {"format": ckpt.FORMAT, "model": "layer", "payload": WritesMarker(marker)}
    with open(path, "wb") as f:
        if writer == "torch.save":
            torch.save(payload, f)
        else:
            pickle.dump(payload, f, protocol=int(writer[-1]))
    with pytest.raises(CheckpointError) as e:
        ckpt.load(path)
    msg = str(e.value)
    if writer == "pickle-4":        # torch's safe unpickler stops at the protocol-4 framing, before any object
        assert msg.startswith(f"cannot read checkpoint {path}: Unsupported operand")
    else:
        assert f"refusing to load {path}" in msg and "system" in msg and "Nothing in it was run" in msg
        assert "training.checkpoint upgrade" not in msg        # never recommend unpacking a file that asks for os.system
    assert not marker.exists()
    # the file really is hostile: an unsafe load runs its code
    with open(path, "rb") as f:
        torch.load(f, weights_only=False) if writer == "torch.save" else pickle.load(f)
    assert marker.exists()


@pytest.mark.filterwarnings("ignore:Detected pickle protocol")
@pytest.mark.parametrize("obj", [np.arange(3), {"rng": np.zeros(2, np.uint32)}])
def test_a_bare_pickle_is_refused_in_our_words_never_with_torchs_unsafe_advice(tmp_path, obj):
    """torch's refusal goes on to suggest weights_only=False or allow-listing the object: the unsafe path.
    The message says only that the file is not a checkpoint this project wrote, and how one it did wrote
    in an older format is converted."""
    path = tmp_path / "raw.pt"
    with open(path, "wb") as f:
        pickle.dump(obj, f, protocol=2)
    with pytest.raises(CheckpointError) as e:
        ckpt.load(path)
    msg = str(e.value)
    assert "is not a checkpoint this project wrote (a bare pickle" in msg and "Nothing in it was run" in msg
    assert "weights_only" not in msg and "safe_globals" not in msg and "torch.serialization" not in msg, msg
    assert "python -m training.checkpoint upgrade FILE converts one" in msg


class Payload:
    """Unpickling this calls ``func(*args)``: a crafted checkpoint's way to run code."""

    def __init__(self, func, args):
        self.func, self.args = func, args

    def __reduce__(self):
        return self.func, self.args


def _hostile(marker):
    import builtins
    import subprocess
    touch = f"open({str(marker)!r}, 'w').close()"
    return {"os.system": (os.system, (f"touch {marker}",)),
            "subprocess.Popen": (subprocess.Popen, (["touch", str(marker)],)),
            "builtins.eval": (builtins.eval, (touch,)),
            "builtins.exec": (builtins.exec, (touch,))}


@pytest.mark.parametrize("name", ["os.system", "subprocess.Popen", "builtins.eval", "builtins.exec"])
@pytest.mark.parametrize("where", ["payload", "rng"])
def test_upgrade_runs_no_code_and_names_what_the_file_asks_for(tmp_path, capsys, name, where):
    """``upgrade`` reads through torch's restricted unpickler: a crafted /1 checkpoint that asks for
    os.system, subprocess.Popen, eval or exec (beside or inside what an old checkpoint holds) is refused,
    naming the object, and nothing runs or is written."""
    marker = tmp_path / "ran"
    func, args = _hostile(marker)[name]
    path = tmp_path / "crafted.pt"
    _old_v1_checkpoint(path)
    ck = torch.load(path, weights_only=False)
    if where == "payload":
        ck["payload"] = Payload(func, args)
    else:                               # hidden inside the numpy RNG state an old checkpoint holds
        ck["rng"]["numpy"] = (ck["rng"]["numpy"][0], Payload(func, args)) + tuple(ck["rng"]["numpy"][2:])
    torch.save(ck, path)
    before = path.read_bytes()
    out = tmp_path / "upgraded.pt"
    assert ckpt.main(["upgrade", str(path), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    shown = {"os.system": "posix.system", "subprocess.Popen": ".Popen",   # pickle records the module Popen says it is in
             "builtins.eval": "builtins.eval", "builtins.exec": "builtins.exec"}[name]
    assert f"refusing to upgrade {path}" in err and shown in err and "nothing in it was run" in err
    assert not marker.exists() and not out.exists() and path.read_bytes() == before
    with pytest.raises(CheckpointError, match="refusing to load") as e:     # load says the same, no upgrade advice
        ckpt.load(path)
    assert shown in str(e.value) and "training.checkpoint upgrade" not in str(e.value)
    assert not marker.exists()


def _old_v1_checkpoint(path):
    """A checkpoint as the previous version wrote it: numpy/Python RNG state tuples (numpy arrays need
    pickle) and torch's TorchVersion string."""
    model, opt = _model_and_optimizer()
    cfg = TrainConfig(model="layer", model_cfg=TINY, steps=4, batch=2, crop=16, spp=2)
    payload = {"format": "denoise-datagen.training-checkpoint/1", "model": "layer", "model_config": model.config,
               "train_config": cfg.to_dict(), "state_dict": model.state_dict(), "optimizer": opt.state_dict(),
               "step": 5, "rng": {"torch": torch.get_rng_state(), "numpy": np.random.get_state(),
                                  "python": random.getstate()},
               "store": STORE, "torch_version": torch.__version__}
    torch.save(payload, path)
    return model


def test_old_checkpoint_is_refused_then_upgrades_once(tmp_path, capsys):
    path = tmp_path / "old.pt"
    model = _old_v1_checkpoint(path)
    with pytest.raises(CheckpointError, match=r"refusing to load .*old\.pt.*numpy") as e:
        ckpt.load(path)
    assert f"python -m training.checkpoint upgrade {path}" in str(e.value)
    assert ckpt.main(["upgrade", str(path), "--out", str(tmp_path / "new.pt")]) == 0
    assert "new.pt" in capsys.readouterr().out
    ck = ckpt.load(tmp_path / "new.pt")
    assert ck["format"] == ckpt.FORMAT and ck["step"] == 5
    assert all(torch.equal(ck["state_dict"][k], v) for k, v in model.state_dict().items())
    ckpt.set_rng_state(ck["rng"])                   # the converted RNG state is usable
    np.random.rand(2)
    assert ckpt.main(["upgrade", str(tmp_path / "missing.pt")]) == 2


def test_corrupt_and_foreign_files_are_named(tmp_path):
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint at all")
    with pytest.raises(CheckpointError, match=r"cannot read checkpoint .*bad\.pt"):
        ckpt.load(bad)
    torch.save({"weights": torch.zeros(2)}, tmp_path / "foreign.pt")
    with pytest.raises(CheckpointError, match=r"foreign\.pt is not a .*checkpoint/2 checkpoint \(format: None\)"):
        ckpt.load(tmp_path / "foreign.pt")


def test_a_torch_whose_safe_loader_can_be_bypassed_is_refused(tmp_path, monkeypatch):
    """torch < 2.6's weights_only loader can be made to run code (CVE-2025-32434): nothing is unpickled."""
    _save(tmp_path / "c.pt")
    monkeypatch.setattr(torch, "__version__", "2.5.1")
    for call in (lambda: ckpt.load(tmp_path / "c.pt"), lambda: ckpt.upgrade(tmp_path / "c.pt")):
        with pytest.raises(CheckpointError, match=r"torch 2\.5\.1 is too old .*CVE-2025-32434.*torch >= 2\.6"):
            call()
