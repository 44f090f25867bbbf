#!/usr/bin/env bash
# Open the MLflow UI on the project's tracking store (http://127.0.0.1:5000).
# Uses .venv/bin/mlflow when present, else the mlflow on PATH.
set -euo pipefail
cd "$(dirname "$0")/.."
MLFLOW=.venv/bin/mlflow
[ -x "$MLFLOW" ] || MLFLOW=$(command -v mlflow || true)
if [ -z "$MLFLOW" ]; then
  echo "mlflow not found: run bash scripts/setup.sh (or pip install mlflow)" >&2
  exit 1
fi
# a moved or copied clone: point the store's recorded artifact locations at this folder first
# (the path goes in as an argument: pasted into the Python source, a folder name could be code)
PY="$(dirname "$MLFLOW")/python"
[ -x "$PY" ] && [ -f mlruns/mlflow.db ] && "$PY" -c \
  'import sys; from party.tracking import relocate_store; relocate_store("sqlite:///" + sys.argv[1])' \
  "$PWD/mlruns/mlflow.db" || true
# the experiments' page in the model-training view (party marks its experiments
# mlflow.experimentKind=custom_model_development); the sidebar's GenAI / Model training switch
# is remembered by the browser
if [ -x "$PY" ] && [ -f mlruns/mlflow.db ]; then
  "$PY" - "$PWD/mlruns/mlflow.db" "${PORT:-5000}" <<'PYEOF' || true
import sqlite3, sys
rows = sqlite3.connect(sys.argv[1]).execute(
    "SELECT experiment_id, name FROM experiments WHERE lifecycle_stage = 'active' AND name != 'Default'").fetchall()
for eid, name in rows:
    print(f"experiment {name}: http://127.0.0.1:{sys.argv[2]}/#/experiments/{eid}/runs")
PYEOF
fi
exec "$MLFLOW" ui --backend-store-uri "sqlite:///$PWD/mlruns/mlflow.db" \
  --default-artifact-root "$PWD/mlruns/artifacts" --host 127.0.0.1 --port "${PORT:-5000}"
