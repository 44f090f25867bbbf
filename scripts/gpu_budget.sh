#!/usr/bin/env bash
# The training-budget curve at the paper's budget, on the CUDA GPUs of one machine (conf/sweep/
# gen_budget_gpu.yaml: ParTY, holistic-only, ParCo-like, parts-only ParTY at 1x, 3x, 9x the CPU
# default's steps and at the paper's 150,000, three training seeds each):
#   bash scripts/gpu_budget.sh [overrides for `party params`, e.g. dataset=humanml3d]
# Sets up, composes params.yaml with trainer=gpu (bf16-mixed), reproduces what the generators
# and the evaluation need (data, texts, tokenizers, tokens, evaluators), runs the grid with one
# worker per GPU (each point on one GPU; scripts/sweep_unattended.sh, resumable: run it again to
# go on), then adds the named-side rate and writes data/ablations/gen_budget_gpu/report.html
# (the metrics against the steps trained). The CPU curve: conf/sweep/gen_budget.yaml.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
export PATH="$PWD/.venv/bin:$PATH" MPLBACKEND=Agg
gpus=$(python -c "import torch; print(torch.cuda.device_count())")
if (( gpus < 1 )); then
  echo "gpu_budget.sh: no CUDA GPU visible (torch.cuda.device_count() = 0); on a CPU run the same curve as" \
       "party gen_ablation generator.ablation.sweep=gen_budget (docs/sweeps.md)" >&2
  exit 1
fi
party params trainer=gpu "$@"
party repro -j 2 embed_texts extract_tokens train_evaluator
PARTY_SWEEP_WORKERS=$gpus PARTY_SWEEP_GPUS=1 bash scripts/sweep_unattended.sh gen_ablation gen_budget_gpu \
  generator.ablation.replications=20 trainer.devices=1 trainer.strategy=auto
out=$(python -c "import yaml; print(yaml.safe_load(open('params.yaml'))['generator']['ablation']['out_dir'])")
python scripts/seed_table.py --grid "$out/gen_budget_gpu" --side
echo "Report: $PWD/$out/gen_budget_gpu/report.html"
