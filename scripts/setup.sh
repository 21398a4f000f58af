#!/usr/bin/env bash
# Idempotent project setup: .venv, CPU/GPU torch, the package, and a shared libLLVM >= 16 for drjit.
# Quick when already done: a stamp file records the hash of pyproject.toml and this script.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
VENV=.venv
STAMP=$VENV/.setup-stamp
want=$(cat pyproject.toml scripts/setup.sh | sha256sum | cut -d' ' -f1)

say() { printf '[setup] %s\n' "$*" >&2; }

# --- 1. libLLVM >= 16 for drjit's LLVM backend (Mitsuba's llvm_ad_rgb variant) ---------------
find_llvm() {
  if [ -n "${DRJIT_LIBLLVM_PATH:-}" ] && [ -f "$DRJIT_LIBLLVM_PATH" ]; then echo "$DRJIT_LIBLLVM_PATH"; return 0; fi
  for v in 21 20 19 18 17 16; do
    for d in /usr/lib/x86_64-linux-gnu /usr/lib/aarch64-linux-gnu /usr/lib /usr/local/lib /usr/lib/llvm-$v/lib; do
      for f in "$d/libLLVM.so.$v.1" "$d/libLLVM-$v.so" "$d/libLLVM.so.$v"; do
        [ -f "$f" ] && { echo "$f"; return 0; }
      done
    done
  done
  return 1
}
if ! llvm=$(find_llvm); then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    say "installing Debian's libllvm19 (drjit needs a shared libLLVM >= 16; libLLVM-15 crashes it)"
    (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libllvm19) >&2
    llvm=$(find_llvm) || { say "libllvm19 installed but libLLVM.so.19 not found"; exit 1; }
  elif command -v nvidia-smi >/dev/null && nvidia-smi -L >/dev/null 2>&1; then
    say "no libLLVM >= 16 found; continuing because a GPU is present (cuda_ad_rgb)"; llvm=""
  else
    say "ERROR: drjit needs a shared libLLVM >= 16 and none was found."
    say "  Install Debian's package 'libllvm19' (apt-get install libllvm19) as root,"
    say "  or point DRJIT_LIBLLVM_PATH at an existing libLLVM.so (>= 16)."
    exit 1
  fi
fi
mkdir -p "$VENV" 2>/dev/null || true
[ -n "$llvm" ] && echo "$llvm" > .llvm-path

if [ -f "$STAMP" ] && [ "$(cat "$STAMP")" = "$want" ] && [ -x "$VENV/bin/python" ]; then
  exit 0
fi

# --- 2. virtual environment and dependencies ----------------------------------------------
[ -x "$VENV/bin/python" ] || { say "creating $VENV"; "$PY" -m venv "$VENV"; }
PIP="$VENV/bin/python -m pip"
$PIP install -q --upgrade pip >&2
if ! "$VENV/bin/python" -c "import torch" 2>/dev/null; then
  if command -v nvidia-smi >/dev/null && nvidia-smi -L >/dev/null 2>&1; then
    say "GPU found: installing torch (CUDA build)"; $PIP install -q torch >&2
  else
    say "no GPU: installing the CPU build torch==2.13.0"
    $PIP install -q torch==2.13.0 >&2
  fi
fi
say "installing the project and its dependencies"
$PIP install -q -e '.[dev]' >&2
echo "$want" > "$STAMP"
say "done ($( "$VENV/bin/python" -c 'import mitsuba, torch, zarr; print("mitsuba", mitsuba.__version__, "torch", torch.__version__, "zarr", zarr.__version__)'))"
