#!/usr/bin/env python3
"""The GPU check: one command on a bare GPU machine, one JSON of figures, written as they come.

    python scripts/device_check.py --build-wheels          # here: the wheels it carries (build/device-wheels)
    python scripts/device_check.py --dry-run               # the plan and {"carried_bytes": ...} of what travels
    python3 scripts/device_check.py --out check.json       # there: every part, within --budget seconds
    python3 scripts/device_check.py --parts realtime,training --budget 380 --out check-1.json   # one of two runs
    python3 scripts/device_check.py --e2e --out e2e.json   # the real job on one GPU alone (= --parts e2e)
    python scripts/device_check.py --smoke [--e2e]         # every path on this CPU at toy sizes (the tests')

The machine it is made for has a GPU, python3 with torch (2.11 on the H200 machines lent to this project)
and none of our packages; nothing can be downloaded there. What it lacks travels beside the checkout as
wheels, in ``build/device-wheels`` (ignored by git; pass it as a carried path): drjit, trimesh, a Mitsuba
wheel slimmed to the variants and plugins used (``cuda_ad_rgb``, ``llvm_ad_rgb``, ``scalar_rgb``; the
plugins our scenes can load: those a render of the check's scenes maps, and every BSDF, emitter and
texture ``scene_gen.to_mitsuba`` can ask for), and the pipeline's own requirements that the machine
lacks (dask, distributed, zarr, numcodecs, google-crc32c, donfig, OpenEXR, tornado, tblib, zict, partd,
locket, cloudpickle, toolz, msgpack, sortedcontainers, click, flip-evaluator: :func:`pipeline_wheels`),
for the machine's Python (``--python``, default 3.12). Scenes are made with ``scene_gen.pymeshlab:
false`` (no blob or boolean meshes, no decimation), so pymeshlab (106 MB) stays home. OIDN's wheel
(pyoidn, 87.6 MB) does not fit beside Mitsuba in the carried 64 MiB, so OIDN is timed on the GPU only
where the machine has pyoidn.

The parts, in the order of their value (``--parts`` runs a subset, in this order); the JSON is written
to ``--out`` after every part and, within the long ones, after every model, so a run cut off by its
time limit still leaves what it measured. One model's failure is that model's entry
(``{"error": "Type: message"}``), never the part's:

- ``realtime``: ms per frame of nbg and wskpn at 1280x720 and of temporal-small and temporal at
  1920x1080 (a recurrent model's step with its state), compiled in bf16 (``torch.compile``; CUDA graphs
  on a GPU: the form ``denoise --compile`` runs), with eager bf16 and fp32 beside it;
  ``training.bench.time_model`` (``python -m training bench --compile``'s function);
- ``training``: steps/s of layer, temporal, nbg and wskpn at their papers' crops and batches, fp32 and
  bf16: ``training.bench.time_training`` (``python -m training bench --train``), the step ``train``
  runs (``device_train_step``, fused Adam, the loss read every 10 steps);
- ``e2e``: the real job: ``python -m pipeline dataset`` of ``configs/gpu-e2e.yaml`` (64 frames at
  256x256 on the LocalCluster's GPU worker, ``cuda_ad_rgb``), ``python -m pipeline validate``,
  ``python -m training train --seconds`` of nbg and layer (bf16), ``python -m training evaluate`` of
  each (and of the noisy input) on the test split: frames/s and each stage's share, the loader's
  wait as a share of a step, steps/s, the evaluation's figures;
- ``render``: ``pipeline.bench_render.run`` (``python -m pipeline bench --only render``'s function) in
  a process per variant, CUDA and (where a libLLVM >= 16 is found) LLVM on all cores: Msamples/s of the
  input loop, the reference and ``mi.render``, the generated scene against the Cornell box; and the
  agreement: max |z| of the CUDA estimate of the check's scene against the LLVM one;
- ``inference``: ms per 1280x720 and 1920x1080 frame of every other model, eager bf16 and fp32
  (``time_model``), and OIDN (``time_oidn``) where the machine has pyoidn;
- ``ddp``: one nccl DistributedDataParallel step (``device_train_step``);
- ``training-compiled``: steps/s of the four families compiled (``train --compile``), bf16, with each
  compile's seconds.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
WHEELS = ROOT / "build" / "device-wheels"
SITE = ROOT / "build" / "device-site"          # the wheels installed there (kept between runs on one machine)
CARRY_LIMIT = 64 * 2 ** 20
BUDGET_S = 380.0                       # seconds for the parts of one run (two runs and a start fit 15 minutes)
VARIANTS = ("cuda_ad_rgb", "llvm_ad_rgb", "scalar_rgb")
# what the check's own process imports that a GPU machine's python3 lacks (trimesh makes the procedural
# meshes; pure Python)
CARRIED = ("drjit", "mitsuba", "trimesh")
# what it imports from the machine's own python3 (torch, and what torch pulls in, besides these);
# setup checks them first and names any that is missing
FROM_MACHINE = ("numpy", "scipy", "torch", "tqdm", "PIL", "yaml")
# the pipeline's requirements (dataset, validate, train, evaluate) whose closure travels, less what the
# GPU machine has (NOTES: torch with its requirements, numpy, scipy, xarray, h5py, scikit-image,
# matplotlib, tqdm, pyyaml, psutil, tensorstore)
PIPELINE_ROOTS = ("dask", "distributed", "zarr", "numcodecs", "google-crc32c", "openexr", "flip-evaluator",
                  "trimesh")
MACHINE_ROOTS = ("torch", "numpy", "scipy", "xarray", "h5py", "scikit-image", "matplotlib", "tqdm", "pyyaml",
                 "psutil", "pillow", "tensorstore")
SCENE_GEN = {"pymeshlab": False}       # the check's scenes: without pymeshlab's meshes (scene_gen.config)
SCENE_SEED, SCENE_KIND = 1, "indoor"
AGREE_RES, AGREE_PASSES, AGREE_PASS_SPP = 48, 16, 64
REALTIME = {"nbg": "720p", "wskpn": "720p", "temporal-small": "1080p", "temporal": "1080p"}
E2E_CONFIG = ROOT / "configs" / "gpu-e2e.yaml"
# what runs where: the GPU machine, and --smoke (every path on this CPU at toy sizes, for the tests)
FULL = {"device": "cuda", "gpu_variant": "cuda_ad_rgb", "render_res": 512, "render_scene_gen": SCENE_GEN,
        "crop": None, "batch_cap": None, "sizes": {"720p": (720, 1280), "1080p": (1080, 1920)}, "ddp": "nccl",
        "compile": True, "step_s": 3.0, "repeats": 5,
        # e2e: the config as it is; each model trained for train_s seconds at its paper's crop and batch
        "e2e_overrides": None, "e2e_precision": "bf16", "e2e_train_s": 25.0, "e2e_loader_workers": 6,
        "e2e_train": {"nbg": (128, 20), "layer": (128, 4)}, "tiny": False, "e2e_env": {"MI_VARIANT": "cuda_ad_rgb"}}
SMOKE = {"device": "cpu", "gpu_variant": "llvm_ad_rgb", "render_res": 16,
         "render_scene_gen": {**SCENE_GEN, "indoor_objects": 8, "outdoor_objects": 8},
         "crop": 16, "batch_cap": 2, "sizes": {"720p": (24, 32), "1080p": (32, 48)}, "ddp": "gloo",
         "compile": False, "step_s": 0.0, "repeats": 1,
         "e2e_overrides": {"name": "gpu-e2e-smoke", "resolution": 16,
                           "scenes": [{"kind": "indoor", "count": 1}, {"kind": "outdoor", "count": 1},
                                      {"kind": "outdoor", "count": 1, "frames": 2}],
                           "render": {"ref_spp": 64, "ref_passes": 8, "ref_min_passes": 8, "time_slices": 2},
                           "scene_gen": {"indoor_objects": 10, "outdoor_objects": 12},
                           "cluster": {"workers": 2}},
         "e2e_precision": "fp32", "e2e_train_s": 2.0, "e2e_loader_workers": 0,
         "e2e_train": {"nbg": (16, 2), "layer": (16, 2)}, "tiny": True,
         "e2e_env": {"MI_VARIANT": "llvm_ad_rgb", "DENOISE_FORCE_CPU": "1"}}
RUN = dict(FULL)
# the Mitsuba wheel's parts no variant we use reads
DROP = re.compile(r"^mitsuba/(include/|mitsuba_stubs/|cmake/|pkgconfig/|python/.*\.pyi$|.*\.pyi$)|^share/")
# plugins kept whatever a render maps: what scene_gen.to_mitsuba and the renderer can ask for
SCENE_PLUGINS = {"path", "independent", "hdrfilm", "box", "gaussian", "perspective", "thinlens", "constant",
                 "twosided", "blendbsdf", "bitmap", "srgb", "area", "point", "envmap", "sunsky", "merge"}

PARTS = [
    ("realtime", "ms per frame of nbg, wskpn (720p), temporal-small, temporal (1080p): compiled bf16, eager "
                 "bf16 and fp32 (training.bench.time_model)"),
    ("training", "steps/s of layer, temporal, nbg, wskpn at their papers' crop and batch, fp32 and bf16 "
                 "(training.bench.time_training: the step train runs)"),
    ("e2e", "pipeline dataset of configs/gpu-e2e.yaml on the GPU worker, validate, train nbg and layer "
            "--seconds, evaluate: frames/s and stage shares, loader wait, steps/s, metrics"),
    ("render", "pipeline.bench_render.run per variant (CUDA; LLVM where libLLVM is found): input loop, "
               "reference, mi.render, Cornell box; CUDA vs LLVM estimates (z)"),
    ("inference", "ms per 720p and 1080p frame of the other models, eager bf16 and fp32, and OIDN"),
    ("ddp", "one DistributedDataParallel step over nccl"),
    ("training-compiled", "steps/s of the four families with train --compile (bf16), and each compile's seconds"),
]
PART_NAMES = [n for n, _ in PARTS]
# the two runs that fit 15 minutes of device time (a ~45 s start, then two calls of at most 420 s)
SPLIT = ("realtime,training,inference", "e2e,render,ddp")


# ---------------------------------------------------------------------------------------------------
# what travels
def carried_files() -> dict[str, int]:
    """Bytes of every file that travels: the checkout's files git tracks or does not ignore, and the
    wheels (an ignored folder, carried by name)."""
    out = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"], cwd=ROOT,
                         capture_output=True, check=True).stdout.decode().split("\0")
    files = {p: (ROOT / p).stat().st_size for p in out if p and (ROOT / p).is_file()}
    if WHEELS.is_dir():
        files |= {str(p.relative_to(ROOT)): p.stat().st_size for p in sorted(WHEELS.iterdir()) if p.is_file()}
    return files


def dry_run(parts: list[str] | None = None) -> dict:
    files = carried_files()
    wheels = {k: v for k, v in files.items() if k.startswith("build/")}
    total = sum(files.values())
    parts = parts or PART_NAMES
    print(f"{'setup':<18} install the carried wheels into build/device-site; the GPU, torch, Mitsuba's variants")
    for name, what in PARTS:
        if name in parts:
            print(f"{name:<18} {what}")
    print(f"carried: {len(files)} files, {total / 2**20:.1f} MiB (wheels {sum(wheels.values()) / 2**20:.1f} MiB) "
          f"of {CARRY_LIMIT / 2**20:.0f} MiB" + ("" if wheels else "; no wheels yet: --build-wheels"))
    print(f"two runs within 15 minutes of device time: --parts {SPLIT[0]} and --parts {SPLIT[1]}")
    res = {"carried_bytes": total, "limit_bytes": CARRY_LIMIT, "fits": total <= CARRY_LIMIT,
           "wheels": wheels, "plan": ["setup", *parts], "split": list(SPLIT)}
    print(json.dumps(res))
    return res


# ---------------------------------------------------------------------------------------------------
# the wheels (built here)
def _norm(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def _closure(roots, python: str | None = None, seen: dict | None = None) -> dict[str, str | None]:
    """``{distribution: version}`` of ``roots`` and everything they require (no extras; markers judged
    for ``python``, e.g. "3.12", default this interpreter), as installed here; None for one that is not
    installed."""
    import importlib.metadata as md

    from packaging.requirements import Requirement
    seen = {} if seen is None else seen
    env = {"extra": ""} | ({"python_version": python, "python_full_version": f"{python}.0"} if python else {})
    for name in roots:
        if _norm(name) in seen:
            continue
        try:
            dist = md.distribution(name)
        except md.PackageNotFoundError:
            seen[_norm(name)] = None
            continue
        seen[_norm(name)] = dist.version
        reqs = [Requirement(r) for r in dist.requires or []]
        _closure([r.name for r in reqs if r.marker is None or r.marker.evaluate(env)], python, seen)
    return seen


def pipeline_wheels(python: str = "3.12") -> dict[str, str]:
    """``{distribution: version}`` that the pipeline needs on the GPU machine (its ``python``) besides
    Mitsuba and drjit: the closure of :data:`PIPELINE_ROOTS` less that of :data:`MACHINE_ROOTS` (the
    versions installed here)."""
    have = _closure(MACHINE_ROOTS, python)
    return {k: v for k, v in _closure(PIPELINE_ROOTS, python).items() if k not in have and v is not None}


def used_plugins(python: str = sys.executable) -> set[str]:
    """The Mitsuba plugins (names) a process loads rendering the check's scenes and a few of the e2e
    config's (LLVM variant), read from its mapped libraries (/proc/self/maps), and
    :data:`SCENE_PLUGINS`."""
    code = ("import sys; sys.path.insert(0, %r); import device_check as d; d._render_all_scenes(); "
            "import json, re; print(json.dumps(sorted({m.group(1) for m in re.finditer(r'/mitsuba/plugins/([A-Za-z0-9_]+)"
            "\\.so', open('/proc/self/maps').read())})))" % str(Path(__file__).parent))
    env = {**os.environ, "PYTHONPATH": str(ROOT), "MI_VARIANT": "llvm_ad_rgb"}
    r = subprocess.run([python, "-c", code], capture_output=True, text=True, env=env, cwd=ROOT, timeout=900)
    if r.returncode != 0:
        raise SystemExit(f"rendering the check's scenes failed: {r.stderr.strip().splitlines()[-3:]}")
    import mitsuba

    from scene_gen.spec import LIGHT_KINDS, MATERIAL_KINDS
    known = {p.stem for p in (Path(mitsuba.__file__).parent / "plugins").glob("*.so")}
    return set(json.loads(r.stdout.strip().splitlines()[-1])) | (SCENE_PLUGINS | set(MATERIAL_KINDS) | set(LIGHT_KINDS)) & known


def slim_mitsuba(src: Path, dst_dir: Path, plugins: set[str], variants=VARIANTS) -> Path:
    """A copy of the Mitsuba wheel ``src`` with only ``variants`` and ``plugins`` (and no headers, stubs
    or CMake files), its RECORD rewritten to match."""
    dst = dst_dir / src.name
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w", zipfile.ZIP_DEFLATED, compresslevel=9) as zout:
        kept, record = [], None
        for info in zin.infolist():
            n = info.filename
            m = re.match(r"^mitsuba/((?:scalar|llvm|cuda)_[a-z_]+)\.cpython-[^/]+\.so$", n)   # a variant's module
            if m and m.group(1) not in variants:
                continue
            m = re.match(r"^mitsuba/plugins/([A-Za-z0-9_]+)\.so$", n)
            if (m and m.group(1) not in plugins) or DROP.match(n):
                continue
            if n.endswith(".dist-info/RECORD"):
                record = info
                continue
            zout.writestr(info, zin.read(n))
            kept.append(n)
        lines = [ln for ln in zin.read(record).decode().splitlines() if ln.split(",")[0] in kept]
        zout.writestr(record, "\n".join(lines + [f"{record.filename},,"]) + "\n")
    return dst


def build_wheels(python_version: str = "3.12") -> list[Path]:
    """Download, for ``python_version``, drjit, Mitsuba and trimesh and the pipeline's wheels
    (:func:`pipeline_wheels`), the versions installed here, and write them to build/device-wheels (the
    Mitsuba wheel slimmed), with the LLVM estimate of the agreement scene (``llvm_estimate.npz``) made here."""
    from importlib.metadata import version
    WHEELS.mkdir(parents=True, exist_ok=True)
    src = ROOT / "build" / "device-wheels-src"
    src.mkdir(parents=True, exist_ok=True)
    pins = {_norm(d): version(d) for d in CARRIED} | pipeline_wheels(python_version)
    tag = python_version.replace(".", "")

    def for_python(w: Path) -> bool:
        return f"-cp{tag}-" in w.name or "-abi3-" in w.name or w.name.endswith("-none-any.whl")

    def wheel_of(dist: str, ver: str) -> Path | None:
        return next((w for w in sorted(src.glob("*.whl")) if for_python(w) and _norm(w.name.split("-")[0]) == dist
                     and w.name.split("-")[1] == ver), None)
    missing = [f"{d}=={v}" for d, v in pins.items() if wheel_of(d, v) is None]
    if missing:
        cmd = [sys.executable, "-m", "pip", "download", "--no-deps", "--only-binary=:all:", "--python-version",
               python_version, "--platform", "manylinux2014_x86_64", "--platform", "manylinux_2_17_x86_64",
               "--platform", "manylinux_2_28_x86_64", "-d", str(src), *missing]
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    for old in WHEELS.glob("*.whl"):
        old.unlink()
    plugins = used_plugins()
    out = []
    for d, v in sorted(pins.items()):
        w = wheel_of(d, v)
        if w is None:
            raise SystemExit(f"no wheel of {d}=={v} for Python {python_version} in {src}")
        out.append(slim_mitsuba(w, WHEELS, plugins) if d == "mitsuba" else Path(shutil.copy2(w, WHEELS / w.name)))
    np_path = WHEELS / "llvm_estimate.npz"
    r = subprocess.run([sys.executable, str(Path(__file__)), "--estimate", str(np_path)], cwd=ROOT,
                       env={**os.environ, "PYTHONPATH": str(ROOT), "MI_VARIANT": "llvm_ad_rgb"}, timeout=900)
    if r.returncode != 0:
        raise SystemExit("the LLVM estimate of the agreement scene failed")
    for p in out + [np_path]:
        print(f"{p.relative_to(ROOT)}: {p.stat().st_size / 2**20:.2f} MiB")
    print(f"plugins kept: {len(plugins)} ({', '.join(sorted(plugins))})")
    return out


# ---------------------------------------------------------------------------------------------------
# scenes
def check_scene(res: int):
    """The generated scene of the check (indoor, seed 1) at ``res``: static, made with
    ``scene_gen.pymeshlab: false`` (no blob or boolean meshes, no decimation: pymeshlab stays home)."""
    import dataclasses

    from scene_gen.config import SceneGenConfig
    from scene_gen.sampling import sample_scene
    spec = sample_scene(SCENE_SEED, SCENE_KIND, num_frames=1, res=res, config=SceneGenConfig.from_dict(SCENE_GEN))
    return dataclasses.replace(spec, objects=tuple(dataclasses.replace(o, velocity=None) for o in spec.objects),
                               shutter=0.0)


def _render_all_scenes() -> None:
    """Every scene and render path of the check at a tiny size, and an indoor and an outdoor scene of the
    e2e config (to find the plugins they load)."""
    from pipeline import render as R
    from pipeline.config import load_config
    from scene_gen.config import SceneGenConfig
    from scene_gen.sampling import sample_scene
    cfg = R.RenderConfig(res=(16, 16), spp=2, ref_spp=8, ref_passes=2, ref_min_passes=2, layer_levels=1)
    R.render_frame(check_scene(16), 0, cfg)
    fs = R.FrameScene(check_scene(16), 0, cfg)
    _cornell(fs.mi, 16)
    gen = SceneGenConfig.from_dict(load_config(E2E_CONFIG).scene_gen)
    tiny = R.RenderConfig(res=(8, 8), spp=1, ref_spp=4, ref_passes=2, ref_min_passes=2, layer_levels=1)
    for kind in ("indoor", "outdoor"):
        R.render_frame(sample_scene(0, kind, num_frames=2, res=8, config=gen), 1, tiny)


def _cornell(mi, res: int):
    d = mi.cornell_box()
    d["sensor"]["film"].update(width=res, height=res, rfilter={"type": "box"})
    return mi.load_dict(d)


def estimate(res: int = AGREE_RES) -> dict:
    """Mean and variance of the mean (float64 HWC) of ``mi.render`` on the check scene, in this
    process's variant: AGREE_PASSES independent passes of AGREE_PASS_SPP."""
    import numpy as np

    from pipeline import render as R
    cfg = R.RenderConfig(res=(res, res), spp=1, ref_spp=0, ref_passes=2, ref_min_passes=2, layer_levels=0)
    fs = R.FrameScene(check_scene(res), 0, cfg)
    runs = np.stack([np.asarray(fs.mi.render(fs.scene, spp=AGREE_PASS_SPP, seed=1000 + i), np.float64)[..., :3]
                     for i in range(AGREE_PASSES)])
    return {"mean": runs.mean(0), "var": runs.var(0, ddof=1) / AGREE_PASSES, "variant": fs.mi.variant()}


def zmax(a: dict, b: dict) -> float:
    """Max |z| of the difference of two estimates: whole-image means and 4x4-block means, per channel
    (tests/test_render.py's test)."""
    import numpy as np

    def blocks(x, k=4):
        h, w = x.shape[:2]
        return x[: h // k * k, : w // k * k].reshape(h // k, k, w // k, k, -1).mean(axis=(1, 3))
    zs = []
    for agg, npx in ((lambda x: x.reshape(-1, x.shape[-1]).mean(0, keepdims=True), a["mean"].shape[0] * a["mean"].shape[1]),
                     (blocks, 16)):
        d = agg(a["mean"]) - agg(b["mean"])
        v = (agg(a["var"]) + agg(b["var"])) / npx
        zs.append(np.abs(d) / np.sqrt(v + 1e-30))
    return float(max(z.max() for z in zs))


def find_libllvm() -> str | None:
    """A shared libLLVM >= 16 on this machine (drjit's LLVM backend), or None."""
    if os.environ.get("DRJIT_LIBLLVM_PATH") and Path(os.environ["DRJIT_LIBLLVM_PATH"]).is_file():
        return os.environ["DRJIT_LIBLLVM_PATH"]
    found = []
    for base in ("/usr/lib", "/usr/local/lib", "/opt", "/usr/lib64"):
        for p in Path(base).rglob("libLLVM*.so*") if Path(base).is_dir() else []:
            m = re.search(r"libLLVM(?:-|\.so\.)(\d+)", p.name)
            if m and int(m.group(1)) >= 16 and p.is_file():
                found.append((int(m.group(1)), str(p)))
    return max(found)[1] if found else None




# ---------------------------------------------------------------------------------------------------
# the parts (there)
def _err(e: BaseException) -> str:
    return f"{type(e).__name__}: {str(e)[:400]}"


def _skipped() -> dict:
    return {"skipped": "out of time"}


def _importable(name: str) -> bool:
    import importlib.util
    return importlib.util.find_spec(name) is not None


def _installed(dist: str) -> bool:
    import importlib.metadata as md
    try:
        md.distribution(dist)
        return True
    except md.PackageNotFoundError:
        return False


def part_setup(state: dict) -> dict:
    """Install the carried wheels the machine lacks into build/device-site (reused while the same wheels
    are there), put it on the path of this process and its children, and say what the machine is."""
    import torch
    wheels = sorted(WHEELS.glob("*.whl"))
    missing = [w for w in wheels if not _installed(w.name.split("-")[0])]
    stamp = SITE / ".wheels"
    listed = "\n".join(w.name for w in missing)
    if missing and not (stamp.is_file() and stamp.read_text() == listed):
        shutil.rmtree(SITE, ignore_errors=True)
        SITE.mkdir(parents=True)
        subprocess.run([sys.executable, "-m", "pip", "install", "--no-index", "--no-deps", "--quiet", "--target",
                        str(SITE), *map(str, missing)], check=True)
        stamp.write_text(listed)
    state["pythonpath"] = os.pathsep.join([str(ROOT), str(SITE)])
    sys.path[:0] = [str(ROOT), str(SITE)]
    import importlib
    importlib.invalidate_caches()
    lacking = [m for m in (*FROM_MACHINE, *CARRIED, "dask", "distributed", "zarr") if not _importable(m)]
    if lacking:
        raise RuntimeError(f"this machine's {sys.executable} lacks {', '.join(lacking)} (carried: "
                           f"{', '.join(w.name for w in wheels) or 'no wheels: build/device-wheels is empty'})")
    if RUN["compile"]:       # compiled kernels kept beside the checkout: a second run on this machine reuses them
        os.environ.setdefault("TORCHINDUCTOR_CACHE_DIR", str(ROOT / "build" / "inductor-cache"))
    import mitsuba as mi
    llvm = find_libllvm()
    state["libllvm"] = llvm
    gpu = {"name": torch.cuda.get_device_name(0), "count": torch.cuda.device_count(),
           "memory_gib": torch.cuda.get_device_properties(0).total_memory / 2**30,
           "bf16": torch.cuda.is_bf16_supported()} if torch.cuda.is_available() else None
    return {"python": platform.python_version(), "torch": torch.__version__, "cuda": torch.version.cuda,
            "gpu": gpu, "cpus": os.cpu_count(), "mitsuba": mi.__version__, "variants": list(mi.variants()),
            "installed": [w.name for w in missing], "libllvm": llvm}


def _env(state: dict, extra: dict | None = None) -> dict:
    """The environment of a child: the checkout and the installed wheels first on its path."""
    path = os.pathsep.join(p for p in (state["pythonpath"], os.environ.get("PYTHONPATH")) if p)
    env = {**os.environ, "PYTHONPATH": path, **(extra or {})}
    if state.get("libllvm"):
        env["DRJIT_LIBLLVM_PATH"] = state["libllvm"]
    return env


def _child(state: dict, variant: str, *args, timeout: float) -> dict:
    """This script in a child process with ``MI_VARIANT=variant``; its last stdout line as JSON."""
    r = _run([sys.executable, str(Path(__file__)), *args], _env(state, {"MI_VARIANT": variant}), timeout)
    if r["rc"] != 0:
        raise RuntimeError(" | ".join(r["tail"]) if r["rc"] is not None else f"timed out after {timeout:.0f} s")
    return json.loads(r["stdout"].strip().splitlines()[-1])


def _run(cmd, env: dict, timeout: float) -> dict:
    """Run ``cmd`` in a session of its own (a LocalCluster's workers with it), killed whole after
    ``timeout`` seconds: ``{"rc" (None when killed), "seconds", "stdout", "tail"}`` (``tail``: the
    last lines of its stderr and stdout)."""
    t = time.perf_counter()
    p = subprocess.Popen([str(c) for c in cmd], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
                         cwd=ROOT, start_new_session=True)
    try:
        out, err = p.communicate(timeout=max(1.0, timeout))
        rc = p.returncode
    except subprocess.TimeoutExpired:
        for sig in (signal.SIGTERM, signal.SIGKILL):
            try:
                os.killpg(p.pid, sig)
                out, err = p.communicate(timeout=15)
                break
            except ProcessLookupError:
                out, err = p.communicate()
                break
            except subprocess.TimeoutExpired:
                continue
        rc = None
    lines = [ln for ln in ((err or "") + "\n" + (out or "")).replace("\r", "\n").splitlines() if ln.strip()]
    return {"rc": rc, "seconds": time.perf_counter() - t, "stdout": out or "", "tail": lines[-6:]}


def _models():
    """``build`` (the papers' sizes; ``--smoke``: each model's test size, ``tiny``), ``get``, ``names``."""
    from training.models import build, get, names
    if RUN["tiny"]:
        def build_tiny(name, **kw):
            return build(name, **{**get(name).tiny, **kw})
        return build_tiny, get, names
    return build, get, names


def _free(dev) -> None:
    import gc

    import torch
    gc.collect()
    if dev.type == "cuda":
        torch.cuda.empty_cache()


def _sync(dev) -> None:
    import torch
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)


def part_realtime(state: dict, left, out: dict, save) -> None:
    """The real-time models at their papers' frame sizes: compiled bf16 (with the eager bf16 figures of
    the same call, ``training.bench.time_model(compile=True)``), then eager fp32."""
    import torch

    from training.bench import time_model
    build, _, _ = _models()
    dev = torch.device(RUN["device"])
    for name, label in REALTIME.items():
        size = RUN["sizes"][label]
        row = out[name] = {"frame": label, "size": list(size)}
        for key, precision, compiled in (("bf16", "bf16", RUN["compile"]), ("fp32", "fp32", False)):
            if left() < (100 if compiled else 15):      # a compile took 67-83 s on the H200
                row[key] = _skipped()
                continue
            t = time.perf_counter()
            try:
                torch.manual_seed(0)
                if compiled:
                    torch._dynamo.reset()                   # a fresh compile per model (training.bench)
                m = build(name)
                row[key] = {**time_model(m, m.input_spec().default_spp, size, RUN["repeats"], dev, precision,
                                         compile=compiled), "seconds": time.perf_counter() - t}
                del m
            except Exception as e:  # noqa: BLE001 - this model's figure
                row[key] = {"error": _err(e), "seconds": time.perf_counter() - t}
            _free(dev)
            save()


def _training(left, out: dict, save, precisions, compiled: bool) -> None:
    import torch

    from training.bench import PAPER_TRAINING, time_training
    build, _, _ = _models()
    dev = torch.device(RUN["device"])
    for name, (crop, batch, spp) in PAPER_TRAINING.items():
        crop, batch = RUN["crop"] or crop, min(batch, RUN["batch_cap"] or batch)
        row = out[name] = {"crop": crop, "batch": batch, "spp": spp}
        for precision in precisions:
            if left() < (150 if compiled else 20):
                row[precision] = _skipped()
                continue
            try:
                torch.manual_seed(0)
                if compiled:
                    torch._dynamo.reset()
                row[precision] = time_training(build(name), crop, batch, spp, dev, precision, RUN["step_s"],
                                               compile=compiled)
            except Exception as e:  # noqa: BLE001 - this model's figure
                row[precision] = {"error": _err(e)}
            _free(dev)
            save()
        if all("steps_per_s" in row.get(p, {}) for p in ("fp32", "bf16")):
            row["bf16_speedup"] = row["bf16"]["steps_per_s"] / row["fp32"]["steps_per_s"]


def part_training(state: dict, left, out: dict, save) -> None:
    _training(left, out, save, ("fp32", "bf16"), compiled=False)


def part_training_compiled(state: dict, left, out: dict, save) -> None:
    if not RUN["compile"]:
        out["skipped"] = "--smoke compiles nothing (train --compile is tested in tests/test_accel.py)"
        return
    _training(left, out, save, ("bf16",), compiled=True)


def part_inference(state: dict, left, out: dict, save) -> None:
    """Every model but the real-time ones, eager, bf16 and fp32, at 720p and 1080p; and OIDN."""
    import torch

    from training.bench import time_model, time_oidn
    build, _, names = _models()
    dev = torch.device(RUN["device"])
    for name in [n for n in names() if n not in REALTIME]:
        row = out[name] = {}
        for precision in ("bf16", "fp32"):
            for label, size in RUN["sizes"].items():
                key = f"{label}_{precision}"
                if left() < 15:
                    row[key] = _skipped()
                    continue
                try:
                    torch.manual_seed(0)
                    m = build(name)
                    row[key] = time_model(m, m.input_spec().default_spp, size, RUN["repeats"], dev, precision)
                    del m
                except Exception as e:  # noqa: BLE001 - this model's figure (out of memory too)
                    row[key] = {"error": _err(e)}
                _free(dev)
        save()
    if dev.type != "cuda":
        out["oidn"] = {"error": "not timed: OIDN is timed on the GPU only (its CPU figure is in make bench)"}
    elif not _importable("pyoidn"):
        out["oidn"] = {"error": "pyoidn is not on this machine (its 87.6 MB wheel does not fit the carried "
                                "64 MiB beside Mitsuba)"}
    else:
        out["oidn"] = {}
        for label, size in RUN["sizes"].items():
            try:
                out["oidn"][label] = time_oidn(size, RUN["repeats"], dev)
            except Exception as e:  # noqa: BLE001
                out["oidn"][label] = {"error": _err(e)}


def part_ddp(state: dict, left, out: dict, save) -> None:
    import torch
    import torch.distributed as td

    from training import accel
    from training.losses import build_loss
    from training.loop import device_train_step
    build, _, _ = _models()
    store = td.FileStore(tempfile.mktemp(prefix="ddp-"), 1)
    td.init_process_group(RUN["ddp"], store=store, rank=0, world_size=1)
    try:
        dev = torch.device("cuda:0" if RUN["device"] == "cuda" else "cpu")
        model = torch.nn.parallel.DistributedDataParallel(accel.prepare(build("nbg"), dev),
                                                          device_ids=[0] if dev.type == "cuda" else None)
        spec = model.module.input_spec()
        b = spec.input_kind.example_batch(4, 1, 128, 128, spec.frames, torch.Generator().manual_seed(0))
        b = {k: v.to(dev) for k, v in b.items()}
        b["reference"] = torch.rand(4, 3, 128, 128, device=dev)
        opt = accel.adam(model.parameters(), 1e-4)
        t = time.perf_counter()
        loss = float(device_train_step(model, opt, build_loss("l1"), b, precision="bf16"))
        _sync(dev)
        out.update({"backend": td.get_backend(), "world": td.get_world_size(), "loss": loss,
                    "seconds": time.perf_counter() - t,
                    "nccl": ".".join(map(str, torch.cuda.nccl.version())) if dev.type == "cuda" else None})
    finally:
        td.destroy_process_group()


def render_child(res: int) -> dict:
    """``pipeline.bench_render.run`` (``python -m pipeline bench --only render``) on the check's scene kind
    and seed, without pymeshlab's meshes, in this process's variant (the child of :func:`part_render`)."""
    from pipeline import bench_render
    out = bench_render.run(seed=SCENE_SEED, kind=SCENE_KIND, res=res, spp=8, ref_passes=2, ref_pass_spp=128,
                           repeats=1, memory=False, e2e_res=0, fph_res=0, scene_gen=RUN["render_scene_gen"])
    import mitsuba as mi
    return {"variant": mi.variant(), "res": res, **out}


def part_render(state: dict, left, out: dict, save) -> None:
    import numpy as np
    gpu = RUN["gpu_variant"]
    variants = [gpu] + (["llvm_ad_rgb"] if state.get("libllvm") and gpu != "llvm_ad_rgb" else [])
    for v in variants:
        if left() < 30:
            out[v] = _skipped()
            continue
        try:
            out[v] = _child(state, v, "--render-child", "--res", str(RUN["render_res"]),
                            *(["--smoke"] if RUN["device"] == "cpu" else []),
                            timeout=max(30.0, left() / 2))
        except Exception as e:  # noqa: BLE001 - recorded, the other variant goes on
            out[v] = {"error": _err(e)}
        save()
    if not state.get("libllvm"):
        out["llvm_ad_rgb"] = {"error": "no shared libLLVM >= 16 on this machine (drjit's LLVM backend)"}
    keys = ("inputs_msamples_per_s", "mi_render_msamples_per_s", "reference_msamples_per_s",
            "mi_render_reference_msamples_per_s", "cornell_msamples_per_s", "generated_msamples_per_s")
    if gpu != "llvm_ad_rgb" and all(k in out.get(v, {}) for v in (gpu, "llvm_ad_rgb") for k in keys):
        out["cuda_vs_llvm_msamples"] = {k: out[gpu][k] / out["llvm_ad_rgb"][k] for k in keys}
    # the agreement: both estimates here, or CUDA here against the LLVM one made where the wheels were built
    if left() < 20:
        out["agreement"] = _skipped()
        return
    try:
        tmp = Path(tempfile.mkdtemp())
        _child(state, gpu, "--estimate", str(tmp / "cuda.npz"), timeout=max(30.0, left() / 2))
        cu = dict(np.load(tmp / "cuda.npz"))
        if state.get("libllvm"):
            _child(state, "llvm_ad_rgb", "--estimate", str(tmp / "llvm.npz"), timeout=max(30.0, left() / 2))
            ll, where = dict(np.load(tmp / "llvm.npz")), "this machine"
        else:
            ll, where = dict(np.load(WHEELS / "llvm_estimate.npz")), "carried (made where the wheels were built)"
        out["agreement"] = {"z_max": zmax(cu, ll), "llvm_estimate": where, "res": AGREE_RES,
                            "spp": AGREE_PASSES * AGREE_PASS_SPP, "pass": "z_max < 5"}
    except Exception as e:  # noqa: BLE001
        out["agreement"] = {"error": _err(e)}


# the e2e part --------------------------------------------------------------------------------------
def e2e_config(work: Path) -> Path:
    """The e2e run's dataset config: configs/gpu-e2e.yaml, with ``--smoke``'s toy sizes merged in."""
    if not RUN["e2e_overrides"]:
        return E2E_CONFIG
    import yaml
    cfg = yaml.safe_load(E2E_CONFIG.read_text())
    for k, v in RUN["e2e_overrides"].items():
        cfg[k] = {**cfg.get(k, {}), **v} if isinstance(v, dict) and isinstance(cfg.get(k), dict) else v
    path = work / "gpu-e2e-smoke.yaml"
    path.write_text(yaml.safe_dump(cfg, sort_keys=False))
    return path


def _dataset_figures(r: dict, summary: Path, store: Path, workers: int) -> dict:
    """Frames/s of the dataset run and each stage's share of its workers' time (the run's summary: render
    time, scene load and kernel compile included, and write time, summed over tasks)."""
    d = {"rc": r["rc"], "wall_s": r["seconds"], "workers": workers}
    if not summary.is_file():
        d["error"] = (f"timed out after {r['seconds']:.0f} s" if r["rc"] is None else "failed") + ": " + \
            " | ".join(r["tail"])
        try:
            from stores import schema
            from stores.writer import complete_flags
            d["complete"] = int(complete_flags(schema.open_group(str(store), check=False)[0]).sum())
            d["frames_per_s_wall"] = d["complete"] / r["seconds"]
        except Exception as e:  # noqa: BLE001 - no store yet
            d["complete"] = f"unknown ({_err(e)})"
        return d
    s = json.loads(summary.read_text())
    t = s.get("timings", {})
    el, render, write = s["elapsed_s"], s["render_s"], t.get("write_s", 0.0)
    busy = el * workers
    d.update({"frames": s["frames"], "complete": s["complete"], "rendered": s["rendered"], "failed": len(s["failed"]),
              "ok": s["ok"], "elapsed_s": el, "frames_per_s": s["rendered"] / el if el else None,
              "frames_per_s_wall": s["rendered"] / r["seconds"], "render_s": render, "write_s": write,
              "share": {"render": render / busy, "write": write / busy, "rest": max(0.0, 1 - (render + write) / busy)},
              "commits": t.get("commits"), "commit_latency_mean_s": t.get("commit_latency_mean_s"),
              "validation_ok": s.get("validation", {}).get("ok")})
    if not s["ok"]:
        d["tail"] = r["tail"]
    return d


def part_e2e(state: dict, left, out: dict, save) -> None:
    """The real job on one GPU (``--smoke``: on this CPU): the dataset, validate, train, evaluate, each as
    its command runs it, in a process of its own (killed whole when it runs out of time)."""
    import torch
    work = Path(tempfile.mkdtemp(prefix="device-check-e2e-"))
    cfg = e2e_config(work)
    out["config"] = str(cfg.relative_to(ROOT)) if cfg.is_relative_to(ROOT) else "configs/gpu-e2e.yaml (--smoke sizes)"
    env, py = _env(state, RUN["e2e_env"]), sys.executable
    store = work / "e2e.zarr"
    models = RUN["e2e_train"]
    after = 45 + len(models) * (RUN["e2e_train_s"] + 60)        # what validation, training and evaluation need
    import yaml
    c = yaml.safe_load(cfg.read_text())
    workers = (torch.cuda.device_count() if RUN["device"] == "cuda" else (c.get("cluster") or {}).get("workers")) or 1
    r = _run([py, "-m", "pipeline", "dataset", "--config", cfg, "--out", store, "--summary-json",
              work / "summary.json"], env, max(30.0, left() - after))
    out["dataset"] = _dataset_figures(r, work / "summary.json", store, workers)
    save()
    r = _run([py, "-m", "pipeline", "validate", store], env, max(20.0, min(300.0, left() - after + 45)))
    out["validate"] = {"ok": r["rc"] == 0, "rc": r["rc"], "seconds": r["seconds"], "tail": r["tail"][-3:]}
    save()
    out["train"], out["evaluate"] = {}, {}
    for i, (model, (crop, batch)) in enumerate(models.items()):
        secs = min(RUN["e2e_train_s"], max(2.0, (left() - 45 - 60 * (len(models) - i)) / (len(models) - i)))
        if left() < secs + 30:
            out["train"][model] = _skipped()
            continue
        run = work / "runs" / model
        tiny = ["--model-cfg", json.dumps(_models()[1](model).tiny)] if RUN["tiny"] else []   # --smoke: test sizes
        r = _run([py, "-m", "training", "train", "--model", model, "--store", store, "--out", run, *tiny,
                  "--steps", "1000000", "--seconds", f"{secs:g}", "--crop", crop, "--batch", batch,
                  "--device", RUN["device"], "--precision", RUN["e2e_precision"], "--workers",
                  RUN["e2e_loader_workers"], "--val-every", "0", "--checkpoint-every", "1000000", "--no-progress",
                  "--skip-bad-frames"], env, secs + 240)
        row = out["train"][model] = {"rc": r["rc"], "seconds": r["seconds"], "train_s": secs, "crop": crop,
                                     "batch": batch, "precision": RUN["e2e_precision"]}
        try:
            res = json.loads(r["stdout"].strip().splitlines()[-1])
            feed = res.get("feed") or {}
            row.update({"steps": res["step"], "loss": res["loss"], "steps_per_s": feed.get("steps_per_s"),
                        "loader_wait_share": feed.get("wait_share"), "loader": feed,
                        "wait_target": "loader_wait_share <= 0.10"})
        except Exception:  # noqa: BLE001 - the run failed: say how
            row["error"] = " | ".join(r["tail"])
        save()
    _e2e_evaluate(work, store, models, env, py, left, out, save)
    shutil.rmtree(work, ignore_errors=True)


def _e2e_evaluate(work: Path, store: Path, models: dict, env: dict, py: str, left, out: dict, save) -> None:
    """The e2e part's evaluations: the input and each trained model on the store's test split."""
    for method in ("input", *models):
        ck = "input" if method == "input" else work / "runs" / method / "checkpoint.pt"
        if method != "input" and not Path(ck).is_file():
            continue
        if left() < 20:
            out["evaluate"][method] = _skipped()
            continue
        res_path = work / f"eval-{method}.json"
        r = _run([py, "-m", "training", "evaluate", "--checkpoint", ck, "--store", store, "--split", "test",
                  "--out", res_path, "--device", RUN["device"], "--precision", RUN["e2e_precision"],
                  "--skip-bad-frames"], env, max(20.0, left() - 5))
        row = out["evaluate"][method] = {"rc": r["rc"], "seconds": r["seconds"]}
        try:
            res = json.loads(res_path.read_text())
            row.update({"frames": len(res.get("frames", [])), "mean": res["mean"]})
        except Exception:  # noqa: BLE001
            row["error"] = " | ".join(r["tail"])
        save()


PART_FNS = {"realtime": part_realtime, "training": part_training, "e2e": part_e2e, "render": part_render,
            "inference": part_inference, "ddp": part_ddp, "training-compiled": part_training_compiled}


class Record:
    """The check's JSON, written to ``path`` (through a temporary file, so a reader never sees half of
    it) each time :meth:`save` is called."""

    def __init__(self, path: str | None):
        self.path = Path(path) if path else None
        self.res: dict = {}

    def save(self) -> None:
        if self.path:
            tmp = self.path.with_name(self.path.name + ".part")
            tmp.write_text(json.dumps(self.res, indent=1, default=str))
            os.replace(tmp, self.path)


def run_check(out_path: str | None, budget: float, parts: list[str] | None = None) -> dict:
    t0 = time.perf_counter()

    def left() -> float:
        return budget - (time.perf_counter() - t0)
    parts = parts or PART_NAMES
    state: dict = {}
    rec = Record(out_path)
    res = rec.res
    res.update({"parts": parts, "budget_s": budget, "smoke": RUN["device"] == "cpu",
                "carried_bytes": sum(carried_files().values()) if (ROOT / ".git").exists() else None,
                "seconds": {}})
    for name in ["setup", *parts]:
        t = time.perf_counter()
        if name == "setup":
            try:
                res["setup"] = part_setup(state)
            except Exception as e:  # noqa: BLE001
                res["setup"] = {"error": _err(e)}
        elif "error" in res["setup"]:
            res[name] = {"error": "setup failed"}
        elif left() < 10:
            res[name] = _skipped()
        else:
            out = res[name] = {}
            try:
                PART_FNS[name](state, left, out, rec.save)
            except Exception as e:  # noqa: BLE001 - one part's failure is a figure too; what it had stays
                out["error"] = _err(e)
        res["seconds"][name] = time.perf_counter() - t
        res["total_seconds"] = time.perf_counter() - t0
        rec.save()
        print(f"[device-check] {name}: {res['seconds'][name]:.1f} s ({left():.0f} s left)", file=sys.stderr,
              flush=True)
    text = json.dumps(res, indent=1, default=str)
    print(text)
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dry-run", action="store_true", help="print the plan and the bytes that would travel")
    ap.add_argument("--build-wheels", action="store_true", help="make build/device-wheels here")
    ap.add_argument("--python", default="3.12", help="the GPU machine's Python (default 3.12)")
    ap.add_argument("--out", help="also write the JSON here (after every part, and within parts after every model)")
    ap.add_argument("--budget", type=float, default=BUDGET_S, help=f"seconds for the parts (default {BUDGET_S:g})")
    ap.add_argument("--parts", help=f"comma-separated parts to run, in the check's order (default all: "
                                    f"{','.join(PART_NAMES)}); two runs that fit 15 minutes: {SPLIT[0]} and {SPLIT[1]}")
    ap.add_argument("--e2e", action="store_true", help="the real job on one GPU alone (the same as --parts e2e)")
    ap.add_argument("--smoke", action="store_true",
                    help="every part on this CPU at toy sizes (LLVM for CUDA, gloo for nccl): the tests' run")
    ap.add_argument("--render-child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--res", type=int, default=FULL["render_res"], help=argparse.SUPPRESS)
    ap.add_argument("--estimate", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    parts = None
    if a.parts or a.e2e:
        asked = [p.strip() for p in (a.parts or "").split(",") if p.strip()] + (["e2e"] if a.e2e else [])
        unknown = sorted(set(asked) - set(PART_NAMES))
        if unknown:
            ap.error(f"--parts: unknown part(s) {', '.join(unknown)}; the parts are {', '.join(PART_NAMES)}")
        parts = [p for p in PART_NAMES if p in asked]
    if a.dry_run:
        return 0 if dry_run(parts)["fits"] else 1
    if a.build_wheels:
        build_wheels(a.python)
        return 0 if dry_run(parts)["fits"] else 1
    if a.smoke:
        RUN.update(SMOKE)
    if a.render_child:
        print(json.dumps(render_child(a.res), default=str))
        return 0
    if a.estimate:
        import numpy as np
        e = estimate()
        np.savez(a.estimate, mean=e["mean"], var=e["var"])
        print(json.dumps({"variant": e["variant"]}))
        return 0
    run_check(a.out, a.budget, parts)
    return 0


if __name__ == "__main__":
    sys.exit(main())
