"""The commands of ``python -m training``: train, evaluate, report, bench, denoise, hard-cases, real-scenes,
fma (see ``--help`` of each). Errors, exit codes and Ctrl-C are :func:`core.cli.run_main`'s; what Ctrl-C
keeps of a training run is said by :func:`_kept`."""
from __future__ import annotations

import argparse
import json
import sys

from core.cli import Program, commands, program_parser
from stores.commands import explain


def _model_cfg(text: str) -> dict:
    """``--model-cfg`` as a dict; strict JSON (``NaN`` and ``Infinity`` are not JSON values). The model
    checks each setting's type when it is built (``training.models.registry.check_settings``)."""
    from .errors import ConfigError

    def no_constant(name):
        raise ConfigError(f"--model-cfg holds {name}, which is not a JSON value (settings must be finite "
                          f"numbers): {text!r}")
    try:
        cfg = json.loads(text, parse_constant=no_constant)
    except json.JSONDecodeError as e:
        raise ConfigError(f"--model-cfg is not valid JSON ({e.msg} at character {e.pos}): {text!r}") from None
    if not isinstance(cfg, dict):
        raise ConfigError(f'--model-cfg must be a JSON object such as \'{{"layers": 3}}\', got {text!r}')
    return cfg


def _train(a) -> int:
    from .cli import config_from
    from .jsonio import dumps
    from .loop import train
    cfg = config_from(a, _model_cfg(a.model_cfg))
    out = a.out or f"data/runs/{a.model}"
    res = train(cfg, a.store, out, progress=not a.no_progress, seconds=a.seconds)
    if res.get("rank", 0) != 0:          # under torchrun: rank 0 speaks for the run
        return 0
    if res["checkpoint"] is None:
        print(f"no step to run (--steps {cfg.steps}); no checkpoint written to {out}", file=sys.stderr)
    print(dumps(res))
    return 0


def _evaluate(a) -> int:
    from .evaluate import evaluate, write_json
    from .jsonio import dumps
    res = evaluate(a.checkpoint, a.store, split=a.split, spp=a.spp, max_frames=a.frames, with_flip=not a.no_flip,
                   skip_bad_frames=a.skip_bad_frames, device=a.device, precision=a.precision, compile=a.compile)
    write_json(res, a.out)
    print(dumps({"method": res["method"], **res["mean"]}))
    return 0


def _report(a) -> int:
    from .report import report
    report(a.runs, a.store, a.out, split=a.split, spp=a.spp, max_frames=a.frames, with_flip=not a.no_flip,
           skip_bad_frames=a.skip_bad_frames, clips_store=a.clips_store, hard_cases=a.hard_cases,
           baseline=a.baseline, real_scenes=a.real_scenes)
    print(f"wrote {a.out}/report.md")
    return 0


def _bench(a) -> int:
    if a.train:
        from .accel import pick_device, precision_for
        from .bench import train_run
        res = train_run(models=a.models or None, seconds=a.seconds, device=a.device,
                        precisions=(precision_for(a.precision, pick_device(a.device)),), crop=a.crop, batch=a.batch,
                        compile=a.compile)
    else:
        from .bench import run
        res = run(size=a.size, spp=a.spp, repeats=a.repeats, models=a.models or None, oidn=not a.no_oidn,
                  device=a.device, precision=a.precision, compile=a.compile)
    if a.json:
        from .jsonio import write
        write(a.json, res)
    return 0


def _denoise(a) -> int:
    from .denoise import denoise_cli
    return denoise_cli(a)


def _fma(a) -> int:
    from .fma import figure10, figure10_markdown
    print(figure10_markdown(figure10()))
    return 0


def _hard_cases(a) -> int:
    from .hardcases import hard_cases_cli
    return hard_cases_cli(a)


def _real_scenes(a) -> int:
    from .realscenes import real_scenes_cli
    return real_scenes_cli(a)


def _model_names() -> str:
    try:
        from .models.registry import names
        return ", ".join(names())
    except Exception:  # noqa: BLE001 - help text only
        return "see training/models"


INFER_COMPILE = ("run the model through torch.compile (the first frame of each size compiles: tens of seconds "
                 "on a CPU)")
INFER_PRECISION = "autocast precision of the forward pass (default auto: bf16 on a GPU that has it, else fp32)"


def _train_parser(sub) -> None:
    from .cli import add_config_options, add_eval
    t = sub.add_parser("train", help="train a denoiser; writes OUT/checkpoint.pt and OUT/metrics.csv (resumes)")
    add_eval(t, ("store", "out"), required=("store",),
             out="run folder for checkpoint.pt and metrics.csv (default: data/runs/MODEL)")
    t.add_argument("--seconds", type=float, default=None,
                   help="stop after this many seconds of training (the checkpoint is written; the same command "
                        "resumes toward --steps)")
    add_config_options(t, skip=("model_cfg",), model="a registered model: " + _model_names())
    t.add_argument("--model-cfg", default="{}", help='JSON model settings, e.g. \'{"layers": 3}\'')
    add_eval(t, ("no_progress",))
    t.set_defaults(run=_train)


def _evaluate_parser(sub) -> None:
    from .cli import add_eval, add_shared
    e = sub.add_parser("evaluate", help="per-frame and mean metrics with ms per megapixel, as JSON")
    e.add_argument("--checkpoint", required=True, help="a checkpoint.pt, or 'input' / 'oidn' for a baseline")
    add_eval(e, ("store", "split", "spp", "frames", "out", "no_flip"), required=("store", "out"),
             spp="input samples per pixel (default: what the checkpoint was trained at; for a baseline all the "
                 "store holds); a count the store does not hold is refused",
             out="JSON file for per-frame and mean metrics")
    add_shared(e, precision=INFER_PRECISION, compile=INFER_COMPILE)
    e.set_defaults(run=_evaluate)


def _report_parser(sub) -> None:
    from .cli import add_eval, add_shared
    r = sub.add_parser("report", help="evaluate runs and baselines; Markdown table, plot and crops")
    r.add_argument("--runs", nargs="+", required=True, help="run folders (each with checkpoint.pt)")
    add_eval(r, ("store", "out", "split", "spp", "frames", "no_flip"), required=("store", "out"),
             out="report folder: report.md, speed_vs_error.png, crops.png",
             spp="input samples per pixel for every run (default: each run at its training spp, with the "
                 "baselines at each of those spp)")
    add_shared(r, names=("skip_bad_frames",))
    r.add_argument("--clips-store", help="also evaluate everything on the test split of this store of moving "
                                         "clips (a section with tPSNR; recurrent models carry their state)")
    r.add_argument("--hard-cases", help="also evaluate everything on each case of this store of "
                                        "configs/hard-cases.yaml (the hard-case table)")
    r.add_argument("--real-scenes", action="append", default=[], metavar="STORE",
                   help="also evaluate everything on this store of scene files (configs/real-scenes.yaml, a user's "
                        "folder): per scene, with intervals, against each method's own input and OIDN; repeatable")
    r.add_argument("--baseline", default=None,
                   help="the one method every other is compared with, by its label in the table (default: each "
                        "method against its own noisy input, at its spp and input kind): paired per-frame "
                        "differences with 95%% intervals")
    r.set_defaults(run=_report)


def _hard_cases_parser(sub) -> None:
    from .cli import add_eval
    h = sub.add_parser("hard-cases", help="every run, OIDN and the noisy input on each case of a hard-case store "
                                          "(configs/hard-cases.yaml): DIR/hard-cases.md and .json")
    h.add_argument("--runs", nargs="*", default=[], help="run folders (each with checkpoint.pt; others are skipped)")
    add_eval(h, ("store", "out", "no_oidn", "frames"), required=("store", "out"),
             store="a store of configs/hard-cases.yaml (every split is evaluated)",
             out="folder for hard-cases.md and hard-cases.json", frames="at most this many frames per split (0: all)")
    h.set_defaults(run=_hard_cases)


def _real_scenes_parser(sub) -> None:
    from .cli import add_eval
    h = sub.add_parser("real-scenes", help="every run, its own noisy input and OIDN on stores of scene files "
                                           "(configs/real-scenes.yaml): DIR/real-scenes.md and .json")
    h.add_argument("--runs", nargs="*", default=[], help="run folders (each with checkpoint.pt; others are skipped)")
    h.add_argument("--store", action="append", required=True, metavar="STORE",
                   help="a store of scene files (every split is evaluated); repeatable (a box- and a "
                        "Gaussian-filtered store, a user's folder)")
    add_eval(h, ("out", "no_oidn", "frames"), required=("out",), out="folder for real-scenes.md and real-scenes.json",
             frames="at most this many frames a store (0: all)")
    h.set_defaults(run=_real_scenes)


def _bench_parser(sub) -> None:
    from .cli import add_eval, add_shared
    b = sub.add_parser("bench", help="inference ms per megapixel of every model and OIDN, in one run")
    b.add_argument("--models", nargs="*", help="registered models to time (default: all)")
    b.add_argument("--size", type=int, default=128, help="square frame size in pixels (default 128)")
    add_eval(b, ("spp",), spp="samples per pixel fed to every model (default: each model's own, 8 or 1)")
    b.add_argument("--repeats", type=int, default=3, help="timed forward passes; the best counts (default 3)")
    b.add_argument("--json", help='write {name: {"ms_per_mp": ...}} (with "oidn") to this file')
    add_eval(b, ("no_oidn",))
    add_shared(b, names=("device", "precision", "compile"), precision=INFER_PRECISION,
               compile="also time every model through torch.compile, with its speed-up and its largest "
                       "difference from the eager output (with --train: the compiled training step)")
    b.add_argument("--train", action="store_true",
                   help="training steps a second instead (the step `train` runs, fused Adam), each family at its "
                        "paper's crop and batch (default models: layer, temporal, nbg, wskpn)")
    b.add_argument("--seconds", type=float, default=3.0,
                   help="with --train: seconds of timed steps a model (default 3)")
    b.add_argument("--crop", type=int, default=None,
                   help="with --train: crop edge for every model (default: the paper's)")
    b.add_argument("--batch", type=int, default=None,
                   help="with --train: at most this batch (default: the paper's)")
    b.set_defaults(run=_bench)


def _denoise_parser(sub) -> None:
    from .cli import add_eval, add_shared
    d = sub.add_parser("denoise", help="apply a trained checkpoint to your own render (EXR images, a store "
                                       "frame or a render-frame .npz), like OIDN's oidnDenoise")
    d.add_argument("--checkpoint", required=True, help="a checkpoint.pt written by `train` (or 'oidn')")
    d.add_argument("--input", help="noisy radiance, an OpenEXR image (per-pixel models), or the .npz of "
                                   "`python -m pipeline render-frame` (any model)")
    d.add_argument("--albedo", help="albedo guide (EXR), when the model uses it")
    d.add_argument("--normal", help="world-space normal guide (EXR), when the model uses it")
    d.add_argument("--depth", help="depth guide (EXR, first channel), when the model uses it")
    add_eval(d, ("store",), store="a Zarr store: denoise its frame --frame (instead of --input)")
    d.add_argument("--frame", type=int, help="frame index in --store")
    add_eval(d, ("spp",), spp="input samples per pixel: the count to take from a store or .npz (default: the "
                              "checkpoint's), or the count an EXR image was rendered at (checked against the "
                              "checkpoint's, with a one-line warning where they differ)")
    d.add_argument("--tile", type=int, default=0,
                   help="denoise in square tiles of this many pixels (with overlap) to bound memory; "
                        "0: automatic (whole image when it fits)")
    add_shared(d, names=("device", "precision", "compile"), precision=INFER_PRECISION, compile=INFER_COMPILE)
    add_eval(d, ("out",), required=("out",), out="denoised radiance, written as OpenEXR")
    d.set_defaults(run=_denoise)


def parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """The parser of ``python -m training``; a command moved to ``studies`` is one line naming where it is
    (a ConfigError, exit 2) instead of argparse's list of choices."""
    moved = _moved(list(argv or []))
    if moved:
        from .errors import ConfigError
        raise ConfigError(moved)
    p = program_parser("python -m training", "Train, evaluate, compare and apply the denoisers.")
    sub = commands(p, dest="cmd")
    for add in (_train_parser, _evaluate_parser, _report_parser, _hard_cases_parser, _real_scenes_parser,
                _bench_parser, _denoise_parser):
        add(sub)
    sub.add_parser("fma", help="figure 10: FMAs against spp").set_defaults(run=_fma)
    return p


# Commands that live in ``studies`` now (they render as well as train): the command and the option that
# names one -> one line naming where it is, instead of argparse's list of choices.
MOVED = {("scaling", None): "python -m training has no command 'scaling': the scaling study is "
                            "`python -m studies scaling` (the same options; see its --help)",
         ("bench", "--scale"): "python -m training bench has no --scale: what a frame costs the stages that read "
                               "the stores as a store grows is `python -m studies bench-scale` (--frames, --source "
                               "and --json as before; see its --help)"}


def _moved(argv: list[str]) -> str | None:
    return next((say for (cmd, opt), say in MOVED.items() if argv[:1] == [cmd] and (opt is None or opt in argv)),
                None)


def _kept(err: KeyboardInterrupt, a, argv: list[str]) -> str:
    """What an interrupted training run kept, said plainly: the checkpoint it resumes from (and its
    step), or that nothing was kept; '' for the other commands. ``a``: None when Ctrl-C came before the
    arguments were parsed. Imports nothing that may be half-imported (a Ctrl-C inside ``import torch``
    leaves torch that cannot be imported again)."""
    loop = sys.modules.get(f"{__package__}.loop")
    if loop is not None and isinstance(err, loop.TrainingInterrupted):
        if err.checkpoint is None:
            return f"at step {err.step}, before any step was trained: nothing was kept"
        return f"at step {err.step}: {err.checkpoint} holds it, and the same command resumes from there"
    if a is None:
        return "before training started: nothing was written" if argv[:1] == ["train"] else ""
    if getattr(a, "cmd", None) != "train":
        return ""
    from pathlib import Path
    ck = Path(a.out or f"data/runs/{a.model}") / "checkpoint.pt"
    if not ck.exists():
        return "no checkpoint was written yet: nothing of the run was kept, the same command starts it again"
    return f"{ck} (its last --checkpoint-every step) is kept, and the same command resumes from it"


def setup(args) -> None:
    from stores.commands import setup as store_setup

    from .accel import tune_allocator
    tune_allocator()
    store_setup(args)


def _again(args) -> str | None:
    """What to do after a full disk: a training run resumes from its last checkpoint."""
    if getattr(args, "cmd", None) == "train":
        return "free space and run the same command again: the run resumes from its last checkpoint.pt"
    return None


PROGRAM = Program(parser=parser, setup=setup, explain=explain, interrupted=_kept, again=_again)
