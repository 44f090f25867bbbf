#!/usr/bin/env bash
# Set up the environment and run the whole test suite (fast tests + the
# end-to-end `dvc repro` test). Extra arguments go to pytest, e.g.
#   bash scripts/test.sh -m "not slow"     # fast tests only
# The SLURM tests run against a one-node cluster this script starts (scripts/slurm_local.sh:
# installs slurm-wlm and munge when root with apt-get) and stops at the end; where it cannot
# start, they skip. PARTY_NO_SLURM=1 leaves SLURM alone.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
bash scripts/system_deps.sh      # blender for the BVH import check (skips cleanly without it)
export PYTHONUNBUFFERED=1 MPLBACKEND=Agg
if [ -z "${PARTY_NO_SLURM:-}" ]; then
  trap 'bash scripts/slurm_local.sh stop' EXIT
  if bash scripts/slurm_local.sh start; then
    eval "$(bash scripts/slurm_local.sh env)"
  else
    echo "no local SLURM cluster: the SLURM tests will skip"
  fi
fi
# Two workers (pytest-xdist), whole files to a worker, handed out in the order tests/conftest.py
# gives (longest first; --no-loadscope-reorder keeps it): the end-to-end file (one `dvc repro`
# fixture and the tests that read it) runs on one from the start while the rest of the suite runs
# on the other. PARTY_TEST_WORKERS=0 runs in this process; `-n N` given here wins.
.venv/bin/python -m pytest -n "${PARTY_TEST_WORKERS:-2}" --dist loadfile --no-loadscope-reorder --durations=25 "$@"
