#!/usr/bin/env bash
# Set up the environment and run the whole pipeline on the embedded default
# (synthetic dataset, offline MiniLM text encoder, CPU-sized budgets):
#   prepare -> cache_part_texts -> embed_texts -> train_vqvae (x3) + train_part_vqvae (x6) -> extract_tokens
#   -> train_evaluator (x3) -> train_generator (per method) -> generate -> evaluate
# Independent stages run side by side (`party repro -j N`, N = PARTY_JOBS, default 2:
# this machine's cores); extra arguments go to `party repro` (stages, -f, -k).
# Ends by printing the metrics tables and where the report and the MLflow runs are.
set -euo pipefail
cd "$(dirname "$0")/.."
start=$(date +%s)
bash scripts/setup.sh
export PATH="$PWD/.venv/bin:$PATH" MPLBACKEND=Agg
party params --check || party params
party repro -j "${PARTY_JOBS:-2}" "$@"
echo
cat data/eval/tables.md
cat <<MSG

Total wall time (install included): $(( $(date +%s) - start )) s
Report:        $PWD/data/eval/report.html (self-contained; open it in a browser)
Metrics:       $PWD/data/eval/metrics.json (dvc metrics show; per-stage times: logs/repro/summary.json)
MLflow runs:   bash scripts/mlflow_ui.sh, then http://127.0.0.1:5000 (store: mlruns/mlflow.db)
MSG
