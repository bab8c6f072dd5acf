#!/usr/bin/env bash
# Set up everything mbcapture needs on a Debian/Ubuntu machine, idempotently:
#   1. a system libLLVM >= 16 for Mitsuba's llvm variants (LLVM 15 crashes Dr.Jit's JIT);
#   2. a virtual environment in .venv with the package (editable) and its test tools.
# Re-running it is cheap: each step is skipped when already done.
set -euo pipefail
cd "$(dirname "$0")/.."

PY=${PYTHON:-python3}
say() { printf 'setup: %s\n' "$*" >&2; }

# --- 1. LLVM -------------------------------------------------------------------------
have_llvm() {
  local f v
  for f in /usr/lib/x86_64-linux-gnu/libLLVM-*.so* /usr/lib/aarch64-linux-gnu/libLLVM-*.so* \
           /usr/lib/llvm-*/lib/libLLVM*.so* /usr/lib64/libLLVM-*.so* /usr/local/lib/libLLVM-*.so*; do
    [ -e "$f" ] || continue
    v=$(basename "$f" | sed -n 's/^libLLVM-\{0,1\}\([0-9][0-9]*\).*/\1/p')
    [ -z "$v" ] && v=$(echo "$f" | sed -n 's#.*/llvm-\([0-9][0-9]*\)/.*#\1#p')
    [ -n "$v" ] && [ "$v" -ge 16 ] && return 0
  done
  return 1
}
if ! have_llvm; then
  if command -v apt-get >/dev/null; then
    SUDO=""
    [ "$(id -u)" -ne 0 ] && SUDO="sudo -n"
    say "installing libllvm19 (Mitsuba's llvm variant needs LLVM >= 16)"
    $SUDO apt-get update -qq >/dev/null
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq libllvm19 >/dev/null
  fi
  have_llvm || { say "no libLLVM >= 16 found; install one (Debian: apt-get install libllvm19) or set DRJIT_LIBLLVM_PATH"; exit 1; }
fi

# --- 2. Python environment -----------------------------------------------------------
if [ ! -x .venv/bin/python ]; then
  say "creating .venv"
  "$PY" -m venv .venv
fi
stamp=.venv/.mbcapture-installed
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
  say "installing mbcapture and its dependencies into .venv"
  .venv/bin/python -m pip install -q --disable-pip-version-check --upgrade pip >/dev/null
  # opencv-contrib-python-headless replaces opencv-python-headless (both install the cv2 package): an
  # environment made before the switch drops the plain wheel first, or the two would overwrite each other
  if .venv/bin/python -m pip show -q opencv-python-headless >/dev/null 2>&1; then
    .venv/bin/python -m pip uninstall -q -y opencv-python-headless opencv-contrib-python-headless >/dev/null
  fi
  .venv/bin/python -m pip install -q --disable-pip-version-check -e '.[test]'
  touch "$stamp"
fi
