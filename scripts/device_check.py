#!/usr/bin/env python3
"""The GPU check: one command on a bare GPU machine, one JSON of figures.

    python scripts/device_check.py --build-wheels        # here: the wheels it carries (build/device-wheels)
    python scripts/device_check.py --dry-run             # the plan, and {"carried_bytes": ...} of what travels
    python3 scripts/device_check.py --out check.json     # there: every figure, within --budget seconds

The machine it is made for has a GPU, python3 with torch (2.11 on the H200 machines lent to this project)
and none of our packages; nothing can be downloaded there. What it lacks travels beside the checkout as
wheels, in ``build/device-wheels`` (ignored by git; pass it as a carried path): drjit, trimesh, and a Mitsuba wheel
slimmed to the variants and plugins used (``cuda_ad_rgb``, ``llvm_ad_rgb``, ``scalar_rgb``; the plugins
our scenes load, found by rendering them here and reading the process's mapped libraries), for the
machine's Python (``--python``, default 3.12). Scenes are loaded with ``triangle_budget: 0`` (no
decimation) and without blob and boolean (CSG) meshes, so pymeshlab (106 MB) stays home. OIDN's wheel (pyoidn) does carry a CUDA device
(``libOpenImageDenoise_device_cuda``) but is 87.6 MB, its core library alone 47 MB compressed: it does not
fit beside Mitsuba in the carried 64 MiB, so OIDN is timed on the GPU only where the machine has pyoidn.

The JSON (also printed) holds, each part timed and each failure recorded without stopping the others:
``render``: Msamples/s of the input loop (radiance and 17 features a sample), the reference (passes with
their standard error) and plain ``mi.render`` on the Cornell box and a generated indoor scene, for the
CUDA variant and, where a libLLVM >= 16 is found there, the LLVM one on all the machine's cores;
``agreement``: max |z| of the CUDA estimate of the generated scene against the LLVM one (image and 4x4
block means; the LLVM estimate made there, else the one made here by --build-wheels and carried);
``training``: steps/s of each family at its paper's crop and batch (layer 128 px x 4, Munkberg sec. 4;
nbg 128 x 20, Meng sec. 5; wskpn 128 x 64, Fan sec. 5; temporal 128 x 4 of 5-frame sequences,
Hasselgren sec. 2.4), fp32 and bf16; ``inference``: ms per 1280x720 and 1920x1080 frame of every
model (bf16 and fp32, and compiled for the real-time ones), and OIDN; ``ddp``: one nccl
DistributedDataParallel step.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import re
import shutil
import subprocess
import sys
import tempfile
import time
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
WHEELS = ROOT / "build" / "device-wheels"
CARRY_LIMIT = 64 * 2 ** 20
BUDGET_S = 450.0                       # of the 8 minutes: the rest is start-up and copying
VARIANTS = ("cuda_ad_rgb", "llvm_ad_rgb", "scalar_rgb")
# what the check imports that a GPU machine's python3 lacks: carried as wheels (trimesh makes the
# procedural meshes; pure Python)
CARRIED = ("drjit", "mitsuba", "trimesh")
# what it imports from the machine's own python3 (torch, and what torch pulls in, besides these);
# setup checks them first and names any that is missing
FROM_MACHINE = ("numpy", "scipy", "torch", "tqdm", "PIL")
PYMESHLAB_KINDS = ("blob", "boolean")       # scene_gen.meshes' kinds made with pymeshlab
SCENE_SEED, SCENE_KIND = 1, "indoor"
AGREE_RES, AGREE_PASSES, AGREE_PASS_SPP = 48, 16, 64
# the papers' training crops and batches (module docstring); frames: a sequence's length (temporal)
TRAINING = {"layer": (128, 4, 8), "temporal": (128, 4, 4), "nbg": (128, 20, 1), "wskpn": (128, 64, 1)}
REALTIME = ("nbg", "wskpn", "temporal-small", "temporal", "layer")
# what runs where: the GPU machine, and --smoke (every path on this CPU at toy sizes, for the tests)
FULL = {"device": "cuda", "gpu_variant": "cuda_ad_rgb", "render_res": 512, "crop": None, "batch_cap": None,
        "sizes": {"720p": (720, 1280), "1080p": (1080, 1920)}, "ddp": "nccl", "compile": True, "step_s": 3.0}
SMOKE = {"device": "cpu", "gpu_variant": "llvm_ad_rgb", "render_res": 16, "crop": 16, "batch_cap": 2,
         "sizes": {"720p": (24, 32), "1080p": (32, 48)}, "ddp": "gloo", "compile": False, "step_s": 0.0}
RUN = dict(FULL)
# the Mitsuba wheel's parts no variant we use reads
DROP = re.compile(r"^mitsuba/(include/|mitsuba_stubs/|cmake/|pkgconfig/|python/.*\.pyi$|.*\.pyi$)|^share/")
SAFE_PLUGINS = {"path", "independent", "hdrfilm", "box", "gaussian", "perspective", "thinlens", "constant"}

PLAN = [
    ("setup", "install the carried wheels into a private folder; the GPU, torch, Mitsuba's variants"),
    ("render", "Msamples/s of the input loop, the reference and mi.render, Cornell box and a generated "
               "scene, CUDA and (libLLVM found) LLVM; CUDA vs LLVM estimates (z)"),
    ("training", "steps/s of layer, temporal, nbg, wskpn at their papers' crop and batch, fp32 and bf16"),
    ("inference", "ms per 1280x720 and 1920x1080 frame of every model (bf16, fp32; compiled for the "
                  "real-time ones) and OIDN"),
    ("ddp", "one DistributedDataParallel step over nccl"),
]


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


def dry_run() -> dict:
    files = carried_files()
    wheels = {k: v for k, v in files.items() if k.startswith("build/")}
    total = sum(files.values())
    for name, what in PLAN:
        print(f"{name:<10} {what}")
    print(f"carried: {len(files)} files, {total / 2**20:.1f} MiB (wheels {sum(wheels.values()) / 2**20:.1f} MiB) "
          f"of {CARRY_LIMIT / 2**20:.0f} MiB" + ("" if wheels else "; no wheels yet: --build-wheels"))
    res = {"carried_bytes": total, "limit_bytes": CARRY_LIMIT, "fits": total <= CARRY_LIMIT,
           "wheels": wheels, "plan": [n for n, _ in PLAN]}
    print(json.dumps(res))
    return res


# ---------------------------------------------------------------------------------------------------
# the wheels (built here)
def used_plugins(python: str = sys.executable) -> set[str]:
    """The Mitsuba plugins (names) a process loads rendering the check's scenes (LLVM variant): read
    from its mapped libraries (/proc/self/maps)."""
    code = ("import sys; sys.path.insert(0, %r); import device_check as d; d._render_all_scenes(); "
            "import json, re; print(json.dumps(sorted({m.group(1) for m in re.finditer(r'/mitsuba/plugins/([A-Za-z0-9_]+)"
            "\\.so', open('/proc/self/maps').read())})))" % str(Path(__file__).parent))
    env = {**os.environ, "PYTHONPATH": str(ROOT), "MI_VARIANT": "llvm_ad_rgb"}
    r = subprocess.run([python, "-c", code], capture_output=True, text=True, env=env, cwd=ROOT, timeout=900)
    if r.returncode != 0:
        raise SystemExit(f"rendering the check's scenes failed: {r.stderr.strip().splitlines()[-3:]}")
    return set(json.loads(r.stdout.strip().splitlines()[-1])) | SAFE_PLUGINS


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
    """Download drjit and Mitsuba (the versions installed here) for ``python_version`` and write drjit's
    wheel and the slimmed Mitsuba wheel to build/device-wheels, with the LLVM estimate of the agreement
    scene (``llvm_estimate.npz``) made here."""
    from importlib.metadata import version
    WHEELS.mkdir(parents=True, exist_ok=True)
    src = ROOT / "build" / "device-wheels-src"
    src.mkdir(parents=True, exist_ok=True)
    pins = [f"{d}=={version(d)}" for d in CARRIED]
    tag = python_version.replace(".", "")
    have = list(src.glob(f"*-cp{tag}-*.whl")) + list(src.glob("*-py3-none-any.whl"))
    if len(have) < len(CARRIED):
        cmd = [sys.executable, "-m", "pip", "download", "--no-deps", "--only-binary=:all:", "--python-version",
               python_version, "--platform", "manylinux_2_28_x86_64", "-d", str(src), *pins]
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    for old in WHEELS.glob("*.whl"):
        old.unlink()
    plugins = used_plugins()
    out = []
    for w in sorted(src.glob(f"*-cp{tag}-*.whl")) + sorted(src.glob("*-py3-none-any.whl")):
        if w.name.startswith("mitsuba-"):
            out.append(slim_mitsuba(w, WHEELS, plugins))
        elif w.name.split("-")[0] in CARRIED:
            out.append(Path(shutil.copy2(w, WHEELS / w.name)))
    np_path = WHEELS / "llvm_estimate.npz"
    r = subprocess.run([sys.executable, str(Path(__file__)), "--estimate", str(np_path)], cwd=ROOT,
                       env={**os.environ, "PYTHONPATH": str(ROOT), "MI_VARIANT": "llvm_ad_rgb"}, timeout=900)
    if r.returncode != 0:
        raise SystemExit("the LLVM estimate of the agreement scene failed")
    for p in out + [np_path]:
        print(f"{p.relative_to(ROOT)}: {p.stat().st_size / 2**20:.1f} MiB")
    print(f"plugins kept: {len(plugins)} ({', '.join(sorted(plugins))})")
    return out


# ---------------------------------------------------------------------------------------------------
# scenes
def check_scene(res: int):
    """The generated scene of the check (indoor, seed 1) at ``res``: static, no decimation, and without
    its blob and boolean (CSG) meshes: decimation, blobs and CSG are pymeshlab's, which stays home."""
    import dataclasses

    from scene_gen.sampling import sample_scene

    def full(mesh):
        return dataclasses.replace(mesh, triangle_budget=0, children=tuple(full(c) for c in mesh.children))

    def csg(mesh) -> bool:
        return mesh.kind in PYMESHLAB_KINDS or any(csg(c) for c in mesh.children)
    spec = sample_scene(SCENE_SEED, SCENE_KIND, num_frames=1, res=res)
    objs = tuple(dataclasses.replace(o, mesh=full(o.mesh), velocity=None) for o in spec.objects if not csg(o.mesh))
    return dataclasses.replace(spec, objects=objs, shutter=0.0)


def _cornell(mi, res: int):
    d = mi.cornell_box()
    d["sensor"]["film"].update(width=res, height=res, rfilter={"type": "box"})
    return mi.load_dict(d)


def _render_all_scenes() -> None:
    """Every scene and render path of the check at a tiny size (to find the plugins they load)."""
    from pipeline import render as R
    cfg = R.RenderConfig(res=(16, 16), spp=2, ref_spp=8, ref_passes=2, ref_min_passes=2, layer_levels=1)
    R.render_frame(check_scene(16), 0, cfg)
    fs = R.FrameScene(check_scene(16), 0, cfg)
    _cornell(fs.mi, 16)


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


def _sync(dev) -> None:
    import torch
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)


def render_figures(res: int = 512, spp: int = 8, ref_passes: int = 2, ref_pass_spp: int = 128) -> dict:
    """Msamples/s in this process's variant (the child of :func:`part_render`)."""
    import numpy as np

    from pipeline import render as R

    def timed(fn, n=2):
        fn()
        best = float("inf")
        for _ in range(n):
            t = time.perf_counter()
            fn()
            best = min(best, time.perf_counter() - t)
        return best
    cfg = R.RenderConfig(res=(res, res), spp=spp, ref_spp=ref_passes * ref_pass_spp, ref_passes=ref_passes,
                         ref_min_passes=ref_passes, layer_levels=0, max_wavefront=max(1 << 21, res * res * spp))
    fs = R.FrameScene(check_scene(res), 0, cfg)
    mi, dr = fs.mi, fs.dr
    n_in, n_ref = res * res * spp, res * res * ref_passes * ref_pass_spp

    def mir(scene, k):
        np.asarray(mi.render(scene, spp=k, seed=7))
    out = {"variant": mi.variant(), "res": res, "threads": int(dr.thread_count()),
           "generated": {"input_loop": n_in / timed(lambda: R.render_inputs(fs)) / 1e6,
                         "mi_render": n_in / timed(lambda: mir(fs.scene, spp)) / 1e6,
                         "reference": n_ref / timed(lambda: R.render_reference(fs), 1) / 1e6,
                         "mi_render_reference": n_ref / timed(lambda: mir(fs.scene, ref_passes * ref_pass_spp), 1) / 1e6}}
    scene = _cornell(mi, res)
    del fs
    out["cornell"] = {"mi_render": n_ref / timed(lambda: mir(scene, ref_passes * ref_pass_spp), 1) / 1e6}
    return out


# ---------------------------------------------------------------------------------------------------
# the parts (there)
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


def part_setup(state: dict) -> dict:
    import torch
    site = Path(tempfile.mkdtemp(prefix="device-check-site-"))
    wheels = sorted(WHEELS.glob("*.whl"))
    missing = [w for w in wheels if not _importable(w.name.split("-")[0])]
    if missing:
        subprocess.run([sys.executable, "-m", "pip", "install", "--no-index", "--no-deps", "--quiet", "--target",
                        str(site), *map(str, missing)], check=True)
    state["pythonpath"] = os.pathsep.join([str(ROOT), str(site)])
    sys.path[:0] = [str(ROOT), str(site)]
    import importlib
    importlib.invalidate_caches()
    lacking = [m for m in (*FROM_MACHINE, *CARRIED) if not _importable(m)]
    if lacking:
        raise RuntimeError(f"this machine's {sys.executable} lacks {', '.join(lacking)} (carried: "
                           f"{', '.join(w.name for w in wheels) or 'no wheels: build/device-wheels is empty'})")
    import mitsuba as mi
    llvm = find_libllvm()
    state["libllvm"] = llvm
    gpu = {"name": torch.cuda.get_device_name(0), "count": torch.cuda.device_count(),
           "memory_gib": torch.cuda.get_device_properties(0).total_memory / 2**30,
           "bf16": torch.cuda.is_bf16_supported()} if torch.cuda.is_available() else None
    return {"python": platform.python_version(), "torch": torch.__version__, "cuda": torch.version.cuda,
            "gpu": gpu, "cpus": os.cpu_count(), "mitsuba": mi.__version__, "variants": list(mi.variants()),
            "installed": [w.name for w in missing], "libllvm": llvm}


def _importable(name: str) -> bool:
    import importlib.util
    return importlib.util.find_spec(name) is not None


def _child(state: dict, variant: str, *args, timeout: float) -> dict:
    env = {**os.environ, "PYTHONPATH": state["pythonpath"], "MI_VARIANT": variant}
    if state.get("libllvm"):
        env["DRJIT_LIBLLVM_PATH"] = state["libllvm"]
    r = subprocess.run([sys.executable, str(Path(__file__)), *args], capture_output=True, text=True, env=env,
                       cwd=ROOT, timeout=timeout)
    if r.returncode != 0:
        raise RuntimeError(" | ".join((r.stderr or r.stdout).strip().splitlines()[-4:]))
    return json.loads(r.stdout.strip().splitlines()[-1])


def part_render(state: dict, left) -> dict:
    import numpy as np
    out = {}
    gpu = RUN["gpu_variant"]
    variants = [gpu] + (["llvm_ad_rgb"] if state.get("libllvm") and gpu != "llvm_ad_rgb" else [])
    for v in variants:
        try:
            out[v] = _child(state, v, "--render-child", "--res", str(RUN["render_res"]),
                            timeout=max(30.0, left() / 2))
        except Exception as e:  # noqa: BLE001 - recorded, the other parts go on
            out[v] = {"error": f"{type(e).__name__}: {e}"}
    if not state.get("libllvm"):
        out["llvm_ad_rgb"] = {"error": "no shared libLLVM >= 16 on this machine (drjit's LLVM backend)"}
    if gpu != "llvm_ad_rgb" and "error" not in out[gpu] and "error" not in out["llvm_ad_rgb"]:
        out["cuda_vs_llvm_msamples"] = {k: out[gpu]["generated"][k] / out["llvm_ad_rgb"]["generated"][k]
                                        for k in out[gpu]["generated"]}
    # the agreement: both estimates here, or CUDA here against the LLVM one made where the wheels were built
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
        out["agreement"] = {"error": f"{type(e).__name__}: {e}"}
    return out


def _models():
    from training.models import build, get, names
    return build, get, names


def part_training(state: dict, left) -> dict:
    import torch

    from training import accel
    from training.losses import build_loss
    from training.loop import train_step
    build, get, _ = _models()
    dev = torch.device(RUN["device"])
    out = {}
    for name, (crop, batch_size, n) in TRAINING.items():
        crop, batch_size = RUN["crop"] or crop, min(batch_size, RUN["batch_cap"] or batch_size)
        row = {"crop": crop, "batch": batch_size, "spp": n}
        for precision in ("fp32", "bf16"):
            if left() < 20:
                row[precision] = "skipped: out of time"
                continue
            torch.manual_seed(0)
            model = accel.prepare(build(name), dev)
            spec = model.input_spec()
            g = torch.Generator().manual_seed(0)
            b = spec.input_kind.example_batch(batch_size, n, crop, crop, spec.frames, g)
            b = {k: v.to(dev) if torch.is_tensor(v) else v for k, v in b.items()}
            with torch.no_grad(), accel.autocast(dev, precision):
                b["reference"] = torch.rand_like(model(b).float())
            opt = torch.optim.Adam(model.parameters(), lr=1e-4)
            loss_fn = build_loss(model.train_defaults.get("loss", "smape"))
            scaler = accel.grad_scaler(dev, precision)

            def step():
                return train_step(model, opt, loss_fn, b, target=spec.input_kind.target(b), precision=precision,
                                  scaler=scaler)
            for _ in range(3):
                step()
            _sync(dev)
            t, k = time.perf_counter(), 0
            while k < 5 or (time.perf_counter() - t < RUN["step_s"] and k < 200):
                loss = step()
                k += 1
            _sync(dev)
            row[precision] = {"steps_per_s": k / (time.perf_counter() - t), "loss": loss}
            del model, opt, b
            if dev.type == "cuda":
                torch.cuda.empty_cache()
        if isinstance(row.get("fp32"), dict) and isinstance(row.get("bf16"), dict):
            row["bf16_speedup"] = row["bf16"]["steps_per_s"] / row["fp32"]["steps_per_s"]
        out[name] = row
    return out


def part_inference(state: dict, left) -> dict:
    import torch

    from training import accel
    build, get, names = _models()
    dev = torch.device(RUN["device"])
    sizes = RUN["sizes"]
    out = {}
    for name in names():
        row = {}
        for precision in ("bf16", "fp32"):
            for label, (h, w) in sizes.items():
                if left() < 15:
                    row[f"{label}_{precision}"] = "skipped: out of time"
                    continue
                try:
                    row[f"{label}_{precision}_ms"] = _time_model(build(name), dev, h, w, precision)
                except torch.cuda.OutOfMemoryError as e:
                    row[f"{label}_{precision}_ms"] = f"out of memory: {str(e)[:120]}"
                if dev.type == "cuda":
                    torch.cuda.empty_cache()
        out[name] = row
    for name in REALTIME if RUN["compile"] else ():                                  # compiled: the real-time models at their sizes
        label, (h, w) = ("720p", sizes["720p"]) if name in ("nbg", "wskpn") else ("1080p", sizes["1080p"])
        if left() < 60:
            out[name][f"{label}_bf16_compiled_ms"] = "skipped: out of time"
            continue
        try:
            torch._dynamo.reset()                          # a fresh compile per model (training.bench)
            out[name][f"{label}_bf16_compiled_ms"] = _time_model(accel.compile_model(build(name).to(dev).for_inference()),
                                                                  dev, h, w, "bf16", ready=True)
        except Exception as e:  # noqa: BLE001
            out[name][f"{label}_bf16_compiled_ms"] = f"{type(e).__name__}: {str(e)[:200]}"
    if dev.type != "cuda":
        out["oidn"] = {"error": "not timed: OIDN is timed on the GPU only (its CPU figure is in make bench)"}
    elif not _importable("pyoidn"):
        out["oidn"] = {"error": "pyoidn is not on this machine (its 87.6 MB wheel does not fit the carried "
                                "64 MiB beside Mitsuba)"}
    else:
        out["oidn"] = _time_oidn(dev, sizes)
    return out


def _time_model(model, dev, h: int, w: int, precision: str, ready: bool = False, repeats: int = 5) -> float:
    import torch

    from training.bench import forward_once
    m = model if ready else model.to(dev).for_inference()
    spec = m.input_spec()
    stepwise = getattr(m, "stepwise", False)
    b = spec.input_kind.example_batch(1, spec.default_spp, h, w, 1 if stepwise else spec.frames,
                                      torch.Generator().manual_seed(0))
    b = {k: v.to(dev) if torch.is_tensor(v) else v for k, v in b.items()}
    state = None
    if stepwise:
        from training.accel import autocast
        with torch.no_grad(), autocast(dev, precision):
            state = m.step(b, None)[1]
    for _ in range(2):
        forward_once(m, b, stepwise, state, dev, precision)
    best = float("inf")
    for _ in range(repeats):
        t = time.perf_counter()
        forward_once(m, b, stepwise, state, dev, precision)
        best = min(best, time.perf_counter() - t)
    return best * 1e3


def _time_oidn(dev, sizes) -> dict:
    import torch

    from training.oidn import oidn_denoise_tensor
    out = {}
    for label, (h, w) in sizes.items():
        c, a, n = (torch.rand(h, w, 3, device=dev) for _ in range(3))
        oidn_denoise_tensor(c, a, n * 2 - 1)
        torch.cuda.synchronize()
        t = time.perf_counter()
        oidn_denoise_tensor(c, a, n * 2 - 1)
        torch.cuda.synchronize()
        out[f"{label}_ms"] = (time.perf_counter() - t) * 1e3
    return out


def part_ddp(state: dict, left) -> dict:
    import torch
    import torch.distributed as td

    from training import accel
    from training.losses import build_loss
    from training.loop import train_step
    build, get, _ = _models()
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
        opt = torch.optim.Adam(model.parameters(), lr=1e-4)
        t = time.perf_counter()
        loss = train_step(model, opt, build_loss("l1"), b, precision="bf16")
        _sync(dev)
        return {"backend": td.get_backend(), "world": td.get_world_size(), "loss": loss,
                "seconds": time.perf_counter() - t,
                "nccl": ".".join(map(str, torch.cuda.nccl.version())) if dev.type == "cuda" else None}
    finally:
        td.destroy_process_group()


def run_check(out_path: str | None, budget: float) -> dict:
    t0 = time.perf_counter()

    def left() -> float:
        return budget - (time.perf_counter() - t0)
    state: dict = {}
    res: dict = {"carried_bytes": sum(carried_files().values()) if (ROOT / ".git").exists() else None}
    parts = [("setup", lambda: part_setup(state)), ("render", lambda: part_render(state, left)),
             ("training", lambda: part_training(state, left)), ("inference", lambda: part_inference(state, left)),
             ("ddp", lambda: part_ddp(state, left))]
    for name, fn in parts:
        t = time.perf_counter()
        if name != "setup" and "error" in res.get("setup", {}):
            res[name] = {"error": "setup failed"}
            continue
        try:
            res[name] = fn()
        except Exception as e:  # noqa: BLE001 - one part's failure is a figure too
            res[name] = {"error": f"{type(e).__name__}: {str(e)[:500]}"}
        res.setdefault("seconds", {})[name] = time.perf_counter() - t
        print(f"[device-check] {name}: {res['seconds'][name]:.1f} s", file=sys.stderr, flush=True)
    res["total_seconds"] = time.perf_counter() - t0
    text = json.dumps(res, indent=1, default=str)
    if out_path:
        Path(out_path).write_text(text)
    print(text)
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dry-run", action="store_true", help="print the plan and the bytes that would travel")
    ap.add_argument("--build-wheels", action="store_true", help="make build/device-wheels here")
    ap.add_argument("--python", default="3.12", help="the GPU machine's Python (default 3.12)")
    ap.add_argument("--out", help="also write the JSON here")
    ap.add_argument("--budget", type=float, default=BUDGET_S, help=f"seconds for the parts (default {BUDGET_S:g})")
    ap.add_argument("--smoke", action="store_true",
                    help="every part on this CPU at toy sizes (LLVM for CUDA, gloo for nccl): the tests' run")
    ap.add_argument("--render-child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--res", type=int, default=FULL["render_res"], help=argparse.SUPPRESS)
    ap.add_argument("--estimate", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.dry_run:
        return 0 if dry_run()["fits"] else 1
    if a.build_wheels:
        build_wheels(a.python)
        return 0 if dry_run()["fits"] else 1
    if a.smoke:
        RUN.update(SMOKE)
    if a.render_child:
        print(json.dumps(render_figures(res=a.res)))
        return 0
    if a.estimate:
        import numpy as np
        e = estimate()
        np.savez(a.estimate, mean=e["mean"], var=e["var"])
        print(json.dumps({"variant": e["variant"]}))
        return 0
    run_check(a.out, a.budget)
    return 0


if __name__ == "__main__":
    sys.exit(main())
