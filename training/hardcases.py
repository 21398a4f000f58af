"""The hard-case table: every trained run, OIDN and the noisy input on every frame of a hard-case store.

``python -m training hard-cases --store data/hard-cases.zarr --runs RUN... --out DIR`` (``make
hard-cases``) evaluates each run with :func:`training.evaluate.evaluate` (its input declaration, its
training spp, recurrent models clip by clip) on every split of the store, and the baselines (``input``:
the noisy per-pixel mean; ``oidn``) at each (spp, input kind) the runs use, as the comparison report
does. It writes ``DIR/hard-cases.md`` and ``DIR/hard-cases.json``: per case (``scene_gen.cases``; a
frame's case comes from ``frames/case`` where set, else from the ``case`` of its SceneSpec in
``frames/scene_json``, '' for ordinary frames) and method, the mean relMSE and PSNR over the case's
frames and whether every output was finite.

Flags (the ``flags`` list; each names the stage, the method and the frame):

- **store** stages, per frame, whatever the method: ``inputs``, ``layers`` or ``reference`` when the
  renderer produced NaN/Inf that the pipeline's rule replaced (``frames/nonfinite_*`` > 0), or when a
  stored array of that stage holds a non-finite value (which the rule forbids);
- **model output** (**noisy input** for the ``input`` baseline, which has no model): a method's output
  holds NaN/Inf on a frame (kind ``non-finite``), or its relMSE on a case is more than
  :data:`OUTLIER_FACTOR` (10) times the median of that method's relMSE over the cases (kind ``error``,
  an error far above its neighbours; the case's worst frame is named);
- **not evaluated**: frames ``validate`` flags (``stores.fitness``, the one check every command applies)
  are left out of the methods' numbers and listed here; a split whose every frame is flagged is left
  out whole (its frames listed), and so is every frame of a store that has no fit frame. The ``nan`` case's frame is fit: its stored
  arrays are finite and its renderer NaNs are its case's purpose (a note, not a problem).

The command exits 1 when it finds a non-finite output, a non-finite stored value or a frame it could not
evaluate (the table says which), 0 otherwise.

PSNR is ``inf`` where a method reproduces the reference exactly (the ``black`` case's input): a perfect
score, not a non-finite output.
"""
from __future__ import annotations

import math
import sys
import warnings
from pathlib import Path

import numpy as np

from .checkpoint import find_runs
from .data import open_store
from .errors import ConfigError, DataError
from .evaluate import baseline_groups, evaluate
from .jsonio import write
from . import stats

OUTLIER_FACTOR = 10.0
SPLITS = ("train", "val", "test")
NO_CASE = "(none)"
# arrays of each store stage checked for finiteness
STAGE_ARRAYS = {"inputs": ("inputs/radiance", "inputs/features", "guides/albedo", "guides/normal", "guides/depth",
                           "guides/motion"),
                "layers": ("layers/radiance",),
                "reference": ("reference/radiance", "reference/stderr")}


def frame_cases(store) -> list[str]:
    """The hard-case tag of every frame of ``store`` ('' for ordinary frames): ``frames/case``, or for a
    store made before it the ``case`` of each clip's SceneSpec (:func:`stores.protocol.scene_cases`)."""
    from stores.protocol import scene_cases
    return [str(c) for c in scene_cases(open_store(store))]


def store_flags(store) -> list[dict]:
    """Store-stage problems of every complete frame: the renderer's replaced NaN/Inf (``frames/nonfinite_*``)
    and non-finite values in a stage's stored arrays. Each: ``{stage, method: 'store', frame, case, detail}``."""
    st = open_store(store)
    cases = frame_cases(st)
    out = []
    replaced = {}
    for stage in STAGE_ARRAYS:
        try:
            replaced[stage] = st.meta_column(f"nonfinite_{stage}")
        except KeyError:                # a format that does not count them (a Noisebase folder): none known
            replaced[stage] = np.zeros(st.num_frames, np.int64)
    for i in st.complete_frames():
        for stage, arrays in STAGE_ARRAYS.items():
            n = int(replaced[stage][i])
            if n:
                out.append({"stage": stage, "method": "store", "frame": i, "case": cases[i] or NO_CASE,
                            "kind": "renderer",
                            "detail": f"the renderer gave {n} NaN/Inf values, replaced by the NaN/Inf rule "
                                      f"(frames/nonfinite_{stage})"})
            for path in (p for p in arrays if st.has_array(p)):     # a Noisebase folder has no layers
                a = np.asarray(st.read_array(path, i))
                bad = int(a.size - np.isfinite(a).sum())
                if bad:
                    out.append({"stage": stage, "method": "store", "frame": i, "case": cases[i] or NO_CASE,
                                "kind": "non-finite", "detail": f"{path} holds {bad} NaN/Inf values"})
    return out


def _splits_with_frames(st) -> list[str]:
    fr = st.split_fractions
    return [s for s in SPLITS if s in fr and st.frames_in_split(s)]


def evaluable_splits(st, unfit) -> tuple[list[str], list[str]]:
    """``(splits to evaluate, splits left out)``: of the splits with frames, those whose every frame is in
    ``unfit`` (frame -> why validate flags it) are left out (``evaluate`` has nothing to take there)."""
    bad = set(unfit)
    keep, out = [], []
    for split in _splits_with_frames(st):
        (out if set(st.frames_in_split(split)) <= bad else keep).append(split)
    return keep, out


def evaluate_frames(method, store, *, label: str, spp=None, baseline_input: str = "pixels", max_frames: int = 0,
                    with_flip: bool = False, progress: bool = True, splits=None) -> dict:
    """``training.evaluate.evaluate`` of ``method`` on ``splits`` of ``store`` (None: every split with
    frames; all frames), with each frame's output finiteness: ``{label, method, spp, input_kind, frames:
    [row + finite + split]}`` (no ``spp`` or ``input_kind`` when no split is evaluated). Frames
    ``evaluate`` refuses are left out (with a warning); :func:`hard_case_report` lists them."""
    st = open_store(store)
    rows, info = [], {}
    for split in (_splits_with_frames(st) if splits is None else splits):
        if progress:
            print(f"hard cases: {label} on {split} of {st.path} ...", flush=True)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            r = evaluate(method, st, split=split, spp=spp, max_frames=max_frames, with_flip=with_flip,
                         keep=tuple(range(st.num_frames)), skip_bad_frames=True, baseline_input=baseline_input)
        images = r.get("images", {})
        for pos, row in enumerate(r["frames"]):
            img = images.get(pos)
            finite = bool(img is not None and np.isfinite(img).all())
            rows.append({**{k: v for k, v in row.items() if not isinstance(v, (list, dict))},
                         "split": split, "finite": finite})
        info = {k: r.get(k) for k in ("method", "spp", "input_kind", "params")}
    return {"label": label, **info, "frames": rows}


def _mean(vals) -> float:
    vals = [float(v) for v in vals]
    return float(np.mean(vals)) if vals else float("nan")


def case_cell(rows: list[dict]) -> dict:
    """One cell of the table from a method's rows on a case's frames: mean relMSE and PSNR with their 95%
    intervals over the frames (a bootstrap with each clip's frames together, ``training.stats``; None
    where a value is not finite, such as the PSNR of an exact output), finiteness and the worst frame."""
    clips = [r.get("clip", r["index"]) for r in rows]
    return {"relmse": _mean(r["relmse"] for r in rows), "psnr": _mean(r["psnr"] for r in rows),
            "relmse_ci95": stats.mean_ci([r["relmse"] for r in rows], clips),
            "psnr_ci95": stats.mean_ci([r["psnr"] for r in rows], clips),
            "finite": all(r["finite"] and math.isfinite(r["relmse"]) for r in rows),
            "frames": [int(r["index"]) for r in rows],
            "worst_frame": int(max(rows, key=lambda r: r["relmse"] if math.isfinite(r["relmse"])
                                   else math.inf)["index"])}


def against_input(rows: list[dict], inputs: list[dict], label: str) -> dict:
    """A method against its own noisy input (the ``input`` baseline at its spp and input kind) on the same
    frames: the paired differences of relMSE (method minus input: below 0 is better) and PSNR (above 0 is
    better) with their intervals (``training.stats.paired_difference``), and the verdict ``beats`` (both
    intervals exclude 0 on the right side), ``exact`` (the input is exact on every frame, as on ``black``,
    and so is the method), ``not exact`` (the input is, the method is not), ``worse`` (an interval excludes
    0 on the wrong side) or ``not shown``."""
    by = {int(r["index"]): r for r in inputs}
    mine = [r for r in rows if int(r["index"]) in by]
    groups = {int(r["index"]): r.get("clip", r["index"]) for r in mine}
    out = {"input": label, "frames": len(mine)}
    if mine and all(by[int(r["index"])]["relmse"] == 0.0 for r in mine):
        out["verdict"] = "exact" if all(r["relmse"] == 0.0 for r in mine) else "not exact"
        return out
    for key, sign in (("relmse", -1.0), ("psnr", 1.0)):
        d = stats.paired_difference({i: by[i][key] for i in groups}, {int(r["index"]): r[key] for r in mine}, groups)
        out[key] = d
    ds = [(out[k], sign) for k, sign in (("relmse", -1.0), ("psnr", 1.0))]
    if all(d and d["shown"] and sign * d["mean"] > 0 for d, sign in ds):
        out["verdict"] = "beats"
    elif any(d and d["shown"] and sign * d["mean"] < 0 for d, sign in ds):
        out["verdict"] = "worse"
    else:
        out["verdict"] = "not shown"
    return out


def summarize(evals: list[dict], cases: list[str], flags: list[dict], store: str = "",
              unfit: dict[int, list[str]] | None = None) -> dict:
    """The hard-case results: per case and method a :func:`case_cell` (means with intervals over the case's
    frames, finiteness) and, for every method that names its ``input_label`` (the label of the ``input``
    evaluation at its spp and input kind), :func:`against_input` under ``vs_input``; plus the flags (store
    flags given, model-output and outlier flags added). ``unfit``: frame -> why validate flags it
    (``stores.fitness.check_frames``), named in "not evaluated" flags."""
    unfit = unfit or {}
    case_names = list(dict.fromkeys(c or NO_CASE for c in cases))
    flags = list(flags)
    table: dict = {c: {} for c in case_names}
    evaluated, rows_of = set(), {}
    for ev in evals:
        by_case: dict = {}
        for row in ev["frames"]:
            evaluated.add(int(row["index"]))
            by_case.setdefault(cases[int(row["index"])] or NO_CASE, []).append(row)
        rows_of[ev["label"]] = by_case
        for c, rows in by_case.items():
            table[c][ev["label"]] = case_cell(rows)
        flags += output_flags(ev, table, cases)
    for ev in evals:
        base = ev.get("input_label")
        for c, rows in rows_of[ev["label"]].items():
            if base and base in rows_of and c in rows_of[base]:
                table[c][ev["label"]]["vs_input"] = against_input(rows, rows_of[base][c], base)
    for i, c in enumerate(cases):
        if evals and i not in evaluated:
            flags.append({"stage": "evaluate", "method": "all", "frame": i, "case": c or NO_CASE,
                          "kind": "not evaluated", "detail": "left out: " + "; ".join(
                              unfit.get(i, ["refused by evaluate (validate flags the frame)"]))})
    return {"store": str(store), "methods": [e["label"] for e in evals], "cases": table, "flags": flags,
            "outlier_factor": OUTLIER_FACTOR,
            "methods_info": {e["label"]: {k: e.get(k) for k in ("method", "spp", "input_kind", "params", "input_label")}
                             for e in evals}}


def output_flags(ev: dict, table: dict, cases: list[str]) -> list[dict]:
    """A method's non-finite outputs (per frame) and cases whose relMSE is more than OUTLIER_FACTOR times the
    median of the method's relMSE over the cases."""
    m = ev["label"]
    stage = "noisy input" if ev.get("method") == "input" else "model output"     # the input baseline has no model
    out = []
    for row in ev["frames"]:
        if not row["finite"] or not math.isfinite(row["relmse"]):
            out.append({"stage": stage, "method": m, "frame": int(row["index"]),
                        "case": cases[int(row["index"])] or NO_CASE, "kind": "non-finite",
                        "detail": "the output holds NaN/Inf" if not row["finite"] else f"relMSE is {row['relmse']}"})
    errs = [row[m]["relmse"] for row in table.values() if m in row and math.isfinite(row[m]["relmse"])]
    med = float(np.median(errs)) if errs else float("nan")
    for c, row in table.items():
        v = row.get(m)
        if v and math.isfinite(v["relmse"]) and len(errs) >= 3 and v["relmse"] > OUTLIER_FACTOR * med:
            out.append({"stage": stage, "method": m, "frame": v["worst_frame"], "case": c, "kind": "error",
                        "detail": f"relMSE {v['relmse']:.4g} is {v['relmse'] / med:.0f}x the median {med:.4g} of "
                                  f"{m} over the cases"})
    return out


def _ci(ci, fmt: str) -> str:
    return f" [{ci[0]:{fmt}}, {ci[1]:{fmt}}]" if ci else ""


def _cell(v: dict | None) -> str:
    if not v:
        return "–"
    if not v["finite"]:
        return "**non-finite**"
    p = v["psnr"]
    ps = "inf" if math.isinf(p) else f"{p:.1f}{_ci(v.get('psnr_ci95'), '.1f')}"
    return f"{v['relmse']:.3g}{_ci(v.get('relmse_ci95'), '.3g')} / {ps}"


VERDICT_MARK = {"beats": "better", "exact": "exact", "not exact": "**not exact**", "worse": "**worse**",
                "not shown": "no difference shown"}


def vs_input_cell(v: dict | None) -> str:
    """Markdown of a cell's ``vs_input``: ΔrelMSE / ΔPSNR with intervals and the verdict."""
    d = (v or {}).get("vs_input")
    if not d:
        return "–"
    if d["verdict"] in ("exact", "not exact"):
        return VERDICT_MARK[d["verdict"]]
    r, p = d.get("relmse"), d.get("psnr")
    rs = f"{r['mean']:+.3g}{_ci(r['ci95'], '+.3g')}" if r else "–"
    ps = f"{p['mean']:+.2f}{_ci(p['ci95'], '+.2f')}" if p else "–"
    return f"{rs} / {ps}: {VERDICT_MARK[d['verdict']]}"


def hard_case_table(results: dict) -> str:
    """Markdown: one row per case, one column per method (``relMSE [95%] / PSNR dB [95%]``,
    ``**non-finite**`` where an output held NaN/Inf), a store column (``finite``, or the stages whose
    NaN/Inf the renderer gave or the store holds); then each method against its own noisy input (paired
    differences with their intervals and the verdict); then the flags, each naming stage, method and frame."""
    methods = results["methods"]
    flags = results["flags"]
    lines = ["| case | store | " + " | ".join(methods) + " |", "|---|---|" + "---|" * len(methods)]
    for c, row in results["cases"].items():
        st = sorted({f["stage"] for f in flags if f["method"] == "store" and f["case"] == c})
        cells = [_cell(row.get(m)) for m in methods]
        lines.append(f"| {c} | {'NaN/Inf in ' + ', '.join(st) if st else 'finite'} | " + " | ".join(cells) + " |")
    lines += ["", "Cells: mean relMSE / PSNR (dB, tone-mapped) over the case's frames, each with its 95% interval "
              "(a bootstrap over the case's clips)."]
    compared = [m for m in methods if results["methods_info"].get(m, {}).get("input_label")]
    if compared:
        lines += ["", "Against its own noisy input (the `input` at the method's spp and input kind, on the same "
                  "frames): ΔrelMSE / ΔPSNR, method minus input, with 95% intervals; better: relMSE lower and PSNR "
                  "higher, both intervals excluding 0.", "",
                  "| case | " + " | ".join(compared) + " |", "|---|" + "---|" * len(compared)]
        for c, row in results["cases"].items():
            lines.append(f"| {c} | " + " | ".join(vs_input_cell(row.get(m)) for m in compared) + " |")
    lines += ["", f"Flags (error: relMSE > {results.get('outlier_factor', OUTLIER_FACTOR):g}x the method's median "
              "over the cases):", ""]
    if not flags:
        lines.append("- none")
    for f in flags:
        lines.append(f"- **{f['case']}**, frame {f['frame']}: stage *{f['stage']}*, method `{f['method']}` "
                     f"({f['kind']}): {f['detail']}")
    return "\n".join(lines)


def baselines_of(evals: list[dict], baseline: str) -> dict[str, str]:
    """Each method's own ``baseline`` (``input`` or ``oidn``): label -> the label of that baseline's
    evaluation at the method's spp and the baseline input of its kind (``training.inputs``), for every
    method that has one (never the baseline's own evaluations); methods without a spp or input kind have none."""
    from .inputs import KINDS

    def key(e):
        return int(e["spp"]), KINDS[e["input_kind"]].baseline_input
    known = [e for e in evals if e.get("spp") is not None and e.get("input_kind") in KINDS]
    found = {key(e): e["label"] for e in known if e.get("method") == baseline}
    return {e["label"]: found[key(e)] for e in known if e.get("method") != baseline and key(e) in found}


def link_inputs(evals: list[dict]) -> None:
    """Set each method's ``input_label``: the label of the ``input`` evaluation at its spp and the baseline
    input of its kind (:func:`baselines_of`), the noisy input it is judged against."""
    own = baselines_of(evals, "input")
    for e in evals:
        if e.get("method") != "input":
            e["input_label"] = own.get(e["label"])


def hard_case_report(runs, store, out, *, with_flip: bool = False, progress: bool = True, oidn: bool = True,
                     max_frames: int = 0) -> dict:
    """Evaluate the runs (folders holding ``checkpoint.pt``), the noisy input and OIDN (at each spp and
    input kind the runs use; the store's spp without runs) on every frame of ``store``; write
    ``out/hard-cases.md`` and ``out/hard-cases.json``. Returns :func:`summarize`'s dict plus ``markdown``."""
    st = open_store(store)
    run_dirs = find_runs(runs)
    if runs and not run_dirs:
        raise ConfigError(f"none of the runs {list(map(str, runs))} holds a checkpoint.pt")
    cases = frame_cases(st)
    unfit = st.check_frames(st.complete_frames())
    splits, left_out = evaluable_splits(st, unfit)
    evals = [evaluate_frames(d / "checkpoint.pt", st, label=d.name, max_frames=max_frames, with_flip=with_flip,
                             progress=progress, splits=splits) for d in run_dirs]
    for name in ("input",) + (("oidn",) if oidn else ()):
        for n, b, tag in baseline_groups([e for e in evals if e.get("spp") is not None], st.layout.spp):
            evals.append(evaluate_frames(name, st, label=name + tag, spp=n, baseline_input=b, max_frames=max_frames,
                                         with_flip=with_flip, progress=progress, splits=splits))
    link_inputs(evals)
    res = summarize(evals, cases, store_flags(st), str(st.path), unfit)
    res["runs"] = [str(d) for d in run_dirs]
    res["splits_evaluated"], res["splits_left_out"] = splits, left_out
    res["markdown"] = hard_case_table(res)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "hard-cases.md").write_text(f"# Hard cases: `{st.path}`\n\n{res['markdown']}\n")
    clean = {k: v for k, v in res.items() if k != "markdown"}
    clean["frames"] = {e["label"]: e["frames"] for e in evals}
    write(out / "hard-cases.json", clean)
    return res


def hard_cases_cli(a) -> int:
    """``python -m training hard-cases`` (arguments from ``training.__main__``)."""
    if a.frames is not None and a.frames < 0:
        raise ConfigError(f"--frames must be >= 0, got {a.frames}")
    try:
        res = hard_case_report(a.runs or [], a.store, a.out, with_flip=False, progress=True, oidn=not a.no_oidn,
                               max_frames=a.frames or 0)
    except DataError:
        raise
    print(res["markdown"])
    print(f"wrote {a.out}/hard-cases.md and {a.out}/hard-cases.json")
    found = problem_flags(res)
    if found:
        print(f"hard cases: {len(found)} problem(s) found (non-finite outputs or stored values, frames left "
              f"out{_left_out_text(res)}): see the flags above", file=sys.stderr)
        return 1
    return 0


def _left_out_text(res: dict) -> str:
    """``; every frame of split 'test' is flagged by validate: ...`` for the splits left out whole, or ''."""
    out = res.get("splits_left_out") or []
    if not out:
        return ""
    if not res.get("splits_evaluated"):
        return "; every frame of the store is flagged by validate: none was evaluated, each is listed"
    names = ", ".join(repr(s) for s in out)
    return (f"; every frame of split{'s' if len(out) > 1 else ''} {names} is flagged by validate: "
            f"{'they were' if len(out) > 1 else 'it was'} left out, each frame listed")


PROBLEM_KINDS = ("non-finite", "not evaluated")


def problem_flags(res: dict) -> list[dict]:
    """The flags that make ``hard-cases`` exit 1: a non-finite output or stored value, a frame left out.
    (The renderer's replaced NaN and relMSE outliers are findings, not failures.)"""
    return [f for f in res["flags"] if f["kind"] in PROBLEM_KINDS]
