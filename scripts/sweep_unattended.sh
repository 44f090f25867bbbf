#!/usr/bin/env bash
# Run (or resume) one ablation grid unattended, e.g. from cron or a systemd timer:
#   bash scripts/sweep_unattended.sh gen_ablation gen_tab5      # party gen_ablation generator.ablation.sweep=gen_tab5
#   bash scripts/sweep_unattended.sh vq_ablation vq_tab4        # party vq_ablation vqvae.ablation.sweep=vq_tab4
# One run at a time per grid (flock); finished points are reused, failed ones retried; the
# log goes to logs/<grid>.log and the status table is appended after every run. Exit status:
# the sweep's (nonzero when a point failed, so cron mails it / systemd marks the unit failed).
# PARTY_SWEEP_WORKERS=N (default 1) starts N workers on the grid at once, each with
# OMP_NUM_THREADS = cores / N: they share its points (party.sweep: each claims the next one
# under a lock on status.json), so N points train side by side. PARTY_SWEEP_GPUS=1 gives worker i
# the GPU i alone (CUDA_VISIBLE_DEVICES=i; start as many workers as GPUs). Grids queue: a second grid
# started while one runs waits for it (logs/.sweeps.lock; PARTY_SWEEP_OVERLAP=1: no waiting).
set -uo pipefail
cd "$(dirname "$0")/.."
stage=${1:?usage: sweep_unattended.sh <gen_ablation|vq_ablation> <grid> [overrides...]}
grid=${2:?usage: sweep_unattended.sh <gen_ablation|vq_ablation> <grid> [overrides...]}
shift 2
case "$stage" in
  gen_ablation) key=generator.ablation.sweep; out=$(.venv/bin/python -c "import yaml;print(yaml.safe_load(open('params.yaml'))['generator']['ablation']['out_dir'])") ;;
  vq_ablation) key=vqvae.ablation.sweep; out=$(.venv/bin/python -c "import yaml;print(yaml.safe_load(open('params.yaml'))['vqvae']['ablation']['out_dir'])") ;;
  *) echo "unknown sweep stage $stage (gen_ablation | vq_ablation)" >&2; exit 2 ;;
esac
mkdir -p logs
log="logs/${grid}.log"
exec 9>"logs/.${grid}.lock"
if ! flock -n 9; then
  echo "$(date -Is) ${grid}: already running, skipped" >> "$log"
  exit 0
fi
# one grid at a time on this machine (two cron entries at the same minute queue instead of
# splitting the cores 4 ways); PARTY_SWEEP_OVERLAP=1 lets grids run side by side
if [[ "${PARTY_SWEEP_OVERLAP:-0}" != 1 ]]; then
  exec 8>"logs/.sweeps.lock"
  if ! flock -n 8; then
    echo "$(date -Is) ${grid}: waiting for another grid to finish" >> "$log"
    flock 8
  fi
fi
echo "$(date -Is) ${grid}: start" >> "$log"
workers=${PARTY_SWEEP_WORKERS:-1}
threads=$(( $(nproc) / workers )); (( threads >= 1 )) || threads=1
pids=()
for ((i = 0; i < workers; i++)); do
  if [[ "${PARTY_SWEEP_GPUS:-0}" == 1 ]]; then export CUDA_VISIBLE_DEVICES=$i; fi
  OMP_NUM_THREADS=$threads .venv/bin/party "$stage" "$key=$grid" "$@" >> "$log" 2>&1 &
  pids+=($!)
  sleep 2   # the first worker claims its point before the next starts
done
rc=0
for pid in "${pids[@]}"; do wait "$pid" || rc=$?; done
.venv/bin/party sweep-status "$out/$grid" >> "$log" 2>&1
echo "$(date -Is) ${grid}: exit $rc" >> "$log"
exit $rc
