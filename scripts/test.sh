#!/usr/bin/env bash
# Set up the environment and run the whole test suite (fast tests + the
# end-to-end `dvc repro` test). Extra arguments go to pytest, e.g.
#   bash scripts/test.sh -m "not slow"     # fast tests only
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
bash scripts/system_deps.sh      # blender for the BVH import check (skips cleanly without it)
export PYTHONUNBUFFERED=1 MPLBACKEND=Agg
exec .venv/bin/python -m pytest "$@"
