#!/usr/bin/env bash
# One idempotent set-up for a fresh Debian machine, used by both README commands and by CI.
# Each step checks first and does nothing when its result is already in place, so a second run
# in a row does no work (it ends with "setup: nothing to do").
#
#   1. Debian packages: libllvm19 (Mitsuba's llvm_ad_rgb; the system LLVM 15 aborts), libusb-1.0-0
#      (pyusb's backend for VIVE USB access); with --tests also chromium (the review page's browser test).
#   2. A virtual environment in .venv (override with DUALHUMAN_VENV).
#   3. A CPU PyTorch when none is present (torch==2.13.0 lies on this kind of machine's disk).
#   4. This package, editable, with its test extras (re-run when pyproject.toml changes).
#   5. The machine's caches, built by `dualhuman body warm` (checked with `body warm --check`):
#      anny's model cache (~790 MB under ~/.cache/anny) and warp's kernel cache (the pipeline's
#      CPU kernels compiled under ~/.cache/warp/<version>, so that no stage compiles on first use).
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${DUALHUMAN_VENV:-.venv}
did=()

apt_pkgs=(libllvm19 libusb-1.0-0)
for arg in "$@"; do
  case "$arg" in
    --tests) apt_pkgs+=(chromium) ;;
    *) echo "setup: unknown option $arg (the one option is --tests)" >&2; exit 2 ;;
  esac
done
missing=()
for p in "${apt_pkgs[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ ${#missing[@]} -gt 0 ]; then
  sudo=""; [ "$(id -u)" -ne 0 ] && sudo="sudo"
  echo "setup: installing Debian packages: ${missing[*]}"
  $sudo apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq -o Dpkg::Use-Pty=0 "${missing[@]}" >/dev/null
  did+=("apt")
fi

if [ ! -x "$VENV/bin/python" ]; then
  echo "setup: creating virtual environment $VENV"
  python3 -m venv "$VENV"
  "$VENV/bin/python" -m pip install -q --upgrade pip
  did+=("venv")
fi
PY="$VENV/bin/python"

if ! "$PY" -c "import torch" >/dev/null 2>&1; then
  echo "setup: installing a CPU PyTorch (torch==2.13.0)"
  "$PY" -m pip install -q torch==2.13.0
  did+=("torch")
fi

stamp="$VENV/.dualhuman-install-stamp"
want=$(cat pyproject.toml | sha256sum | cut -d' ' -f1)
if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ] || ! "$PY" -c "import dualhuman_builder.cli" >/dev/null 2>&1; then
  echo "setup: installing dualhuman-builder with its test extras"
  # the build backend's notices go to a log, shown only if the install fails
  if ! "$PY" -m pip install -q -e '.[test]' > "$VENV/pip-install.log" 2>&1; then
    cat "$VENV/pip-install.log" >&2
    exit 1
  fi
  echo "$want" > "$stamp"
  did+=("package")
fi

if ! "$VENV/bin/dualhuman" body warm --check >/dev/null 2>&1; then
  echo "setup: building the anny body-model cache and warp's kernel cache (once per machine, a few minutes)"
  "$VENV/bin/dualhuman" body warm
  did+=("caches")
fi

if [ ${#did[@]} -eq 0 ]; then
  echo "setup: nothing to do"
else
  echo "setup: done (${did[*]})"
fi
