#!/usr/bin/env bash
# Create .venv (if missing) and install party with its dev extras into it.
# Idempotent: a second run only checks that everything is installed.
#
# Installer: uv (from the package index, into .venv) by default: the same requirements as pip,
# resolved the way pip does (highest version across every configured index), with bytecode
# compiled as pip does, in ~60 s cold here instead of pip's ~145 s (most of it unpacking
# torch's 5 GB of CUDA wheels). pip's sources (indexes, local wheel folders, constraints) are
# passed on (scripts/pip_sources.py) through uv's environment, never its command line (an index
# URL may hold credentials; a command line is readable by every user). PARTY_INSTALLER=pip uses
# pip; a failed uv install falls back to pip.
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
  local listing
  if ! .venv/bin/python -m pip install -q "uv>=0.9" 2>/dev/null; then
    echo "setup.sh: uv is not installable here" >&2; return 1
  fi
  if ! listing=$(.venv/bin/python scripts/pip_sources.py); then
    echo "setup.sh: could not read pip's configured sources for uv" >&2; return 1
  fi
  (  # UV_*=... lines (none configured: none), exported (a builtin: no command line) to uv only
    while IFS= read -r a; do
      case "$a" in
        "") ;;
        UV_INDEX_URL=*|UV_EXTRA_INDEX_URL=*|UV_FIND_LINKS=*|UV_CONSTRAINT=*) export "$a" ;;
        *) echo "setup.sh: unexpected line from scripts/pip_sources.py" >&2; exit 1 ;;
      esac
    done <<< "$listing"
    exec .venv/bin/python -m uv pip install -q --python .venv/bin/python --compile-bytecode \
      --index-strategy unsafe-best-match -e ".[dev]"
  )
}
if [ "${PARTY_INSTALLER:-uv}" != uv ]; then
  pip_install
elif ! uv_install; then
  echo "setup.sh: uv could not install the requirements; installing with pip" >&2
  pip_install
fi
.venv/bin/python -c "import torch, torchvision, lightning, mlflow, dvc, hydra, open_clip; print('party env ok: torch', torch.__version__)"
