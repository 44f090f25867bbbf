#!/usr/bin/env bash
# Create .venv (if missing) and install party with its dev extras into it.
# Idempotent: a second run only checks that everything is installed.
#
# Installer: uv (from the package index, into .venv) by default: the same requirements as pip,
# resolved the way pip does (highest version across every configured index), with bytecode
# compiled as pip does, in ~60 s cold here instead of pip's ~145 s (most of it unpacking
# torch's 5 GB of CUDA wheels). pip's sources (indexes, local wheel folders, constraints) are
# passed on (scripts/pip_sources.py). PARTY_INSTALLER=pip uses pip; a failed uv install falls
# back to pip.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
pip_install() {
  .venv/bin/python -m pip install -q --upgrade pip
  .venv/bin/python -m pip install -q -e ".[dev]"
}
uv_install() {
  local listing sources=()
  if ! .venv/bin/python -m pip install -q "uv>=0.9" 2>/dev/null; then
    echo "setup.sh: uv is not installable here" >&2; return 1
  fi
  if ! listing=$(.venv/bin/python scripts/pip_sources.py); then
    echo "setup.sh: could not read pip's configured sources for uv" >&2; return 1
  fi
  while IFS= read -r a; do [ -n "$a" ] && sources+=("$a"); done <<< "$listing"   # none configured: no arguments
  .venv/bin/python -m uv pip install -q --python .venv/bin/python --compile-bytecode \
    --index-strategy unsafe-best-match "${sources[@]}" -e ".[dev]"
}
if [ "${PARTY_INSTALLER:-uv}" != uv ]; then
  pip_install
elif ! uv_install; then
  echo "setup.sh: uv could not install the requirements; installing with pip" >&2
  pip_install
fi
.venv/bin/python -c "import torch, torchvision, lightning, mlflow, dvc, hydra, open_clip; print('party env ok: torch', torch.__version__)"
