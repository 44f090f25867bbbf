#!/usr/bin/env bash
# Set up the environment and run the whole pipeline on the embedded default
# (synthetic dataset, offline MiniLM text encoder, CPU-sized budgets):
#   prepare -> cache_part_texts -> embed_texts -> train_vqvae -> extract_tokens
#   -> train_evaluator -> evaluate
# Results: data/ (DVC outputs), mlruns/ (MLflow, open with scripts/mlflow_ui.sh).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
export PATH="$PWD/.venv/bin:$PATH" MPLBACKEND=Agg
party params --check || party params
dvc repro "$@"
dvc metrics show || true
