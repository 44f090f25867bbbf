#!/usr/bin/env bash
# Open the MLflow UI on the project's tracking store (http://127.0.0.1:5000).
set -euo pipefail
cd "$(dirname "$0")/.."
exec .venv/bin/mlflow ui --backend-store-uri "sqlite:///$PWD/mlruns/mlflow.db" \
  --default-artifact-root "$PWD/mlruns/artifacts" --host 127.0.0.1 --port "${PORT:-5000}"
