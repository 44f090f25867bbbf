#!/usr/bin/env bash
# A one-node SLURM cluster on this machine, for the tests of the SLURM path (sweeps as job
# arrays, DDP through srun, requeue after preemption) and for trying party's cluster commands
# before using a real cluster.
#
#   bash scripts/slurm_local.sh start     # install (root + apt only, if missing), configure, start, wait idle
#   eval "$(bash scripts/slurm_local.sh env)"   # SLURM_CONF for sbatch/squeue/srun in this shell
#   bash scripts/slurm_local.sh status    # sinfo of the local cluster; exit 1 when it is down
#   bash scripts/slurm_local.sh stop      # stop the daemons by their pids
#
# Everything lives in $PARTY_SLURM_DIR (default /tmp/party-slurm): slurm.conf, state, spool,
# logs, pid files. The node is this host with its CPUs and 90% of its memory; no accounting
# database (`sacct` does not work here; `squeue` and `scontrol show job` do). Munge, slurmctld and
# slurmd run as the calling user; starting munge needs root unless munged already runs.
# Ports: PARTY_SLURM_PORT (slurmctld, default 6817) and the next one (slurmd).
set -euo pipefail
D="${PARTY_SLURM_DIR:-/tmp/party-slurm}"
PORT="${PARTY_SLURM_PORT:-6817}"
CONF="$D/slurm.conf"
HOST="$(hostname -s)"

log() { echo "[slurm_local] $*"; }

have_slurm() { command -v slurmctld >/dev/null 2>&1 && command -v slurmd >/dev/null 2>&1 \
  && command -v sbatch >/dev/null 2>&1 && command -v munged >/dev/null 2>&1; }

install() {
  have_slurm && return 0
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    log "installing slurm-wlm and munge (Debian packages) ..."
    (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
      slurm-wlm munge) >"${TMPDIR:-/tmp}/party_slurm_install.log" 2>&1 \
      || { log "could not install slurm-wlm/munge (see ${TMPDIR:-/tmp}/party_slurm_install.log)"; return 1; }
  else
    log "slurm-wlm and munge are not installed and this is not root with apt-get: install them"; return 1
  fi
}

pid_of() { [ -f "$D/$1.pid" ] && kill -0 "$(cat "$D/$1.pid")" 2>/dev/null && cat "$D/$1.pid"; }

write_conf() {
  local cpus mem_mb
  cpus="$(nproc)"
  mem_mb="$(awk '/MemTotal/ {printf "%d", $2 / 1024 * 0.9}' /proc/meminfo)"
  mkdir -p "$D/state" "$D/spool" "$D/log"
  cat >"$CONF" <<EOF
# written by scripts/slurm_local.sh: a one-node cluster on $HOST
ClusterName=party
SlurmctldHost=$HOST
SlurmctldPort=$PORT
SlurmdPort=$((PORT + 1))
SlurmUser=$(id -un)
SlurmdUser=$(id -un)
AuthType=auth/munge
# a requeued job waits this long before it starts again (SLURM's default 120 s)
AuthInfo=cred_expire=10
StateSaveLocation=$D/state
SlurmdSpoolDir=$D/spool
SlurmctldPidFile=$D/slurmctld.pid
SlurmdPidFile=$D/slurmd.pid
SlurmctldLogFile=$D/log/slurmctld.log
SlurmdLogFile=$D/log/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
MpiDefault=none
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_CPU
AccountingStorageType=accounting_storage/none
JobAcctGatherType=jobacct_gather/none
JobCompType=jobcomp/none
ReturnToService=2
# a requeued or cancelled job's processes get SIGTERM, then SIGKILL this many seconds later
KillWait=10
# finished jobs stay visible to squeue/scontrol this long
MinJobAge=600
SchedulerParameters=batch_sched_delay=0,sched_min_interval=100000
NodeName=$HOST CPUs=$cpus RealMemory=$mem_mb State=UNKNOWN
PartitionName=local Nodes=$HOST Default=YES MaxTime=INFINITE State=UP
EOF
}

start_munge() {
  if pgrep -x munged >/dev/null 2>&1; then return 0; fi
  [ -f /etc/munge/munge.key ] || { log "no /etc/munge/munge.key: create one (mungekey -c) or reinstall munge"; return 1; }
  mkdir -p /run/munge /var/log/munge /var/lib/munge
  chown -R "$(id -un)" /run/munge /var/log/munge /var/lib/munge 2>/dev/null || true
  if [ "$(id -u)" = 0 ]; then
    munged --force
  else
    munged
  fi
}

wait_idle() {
  local t0=$SECONDS
  while (( SECONDS - t0 < ${PARTY_SLURM_WAIT:-60} )); do
    state="$(SLURM_CONF="$CONF" sinfo -h -n "$HOST" -o %T 2>/dev/null || true)"
    case "$state" in idle*|mixed*|allocated*) log "node $HOST $state after $((SECONDS - t0)) s"; return 0 ;; esac
    sleep 0.5
  done
  log "node $HOST not idle after ${PARTY_SLURM_WAIT:-60} s (state '${state:-none}'); last log lines:"
  tail -n 15 "$D/log/slurmctld.log" "$D/log/slurmd.log" 2>/dev/null || true
  return 1
}

cmd_start() {
  local t0=$SECONDS
  install
  if pid_of slurmctld >/dev/null && pid_of slurmd >/dev/null; then
    log "already running (slurmctld $(pid_of slurmctld), slurmd $(pid_of slurmd))"
    wait_idle
    return
  fi
  write_conf
  start_munge
  slurmctld -f "$CONF" -c -i            # -c: a clean state (no jobs of an earlier run)
  SLURM_CONF="$CONF" slurmd -f "$CONF" -c -N "$HOST"
  wait_idle
  log "started in $((SECONDS - t0)) s; SLURM_CONF=$CONF (eval \"\$(bash scripts/slurm_local.sh env)\")"
}

cmd_stop() {
  local any=0
  for d in slurmd slurmctld; do
    if p="$(pid_of "$d")"; then
      kill "$p"; any=1
      for _ in $(seq 50); do kill -0 "$p" 2>/dev/null || break; sleep 0.1; done
      kill -0 "$p" 2>/dev/null && kill -9 "$p"
      log "stopped $d (pid $p)"
    fi
  done
  [ "$any" = 1 ] || log "not running"
}

case "${1:-}" in
  start) cmd_start ;;
  stop) cmd_stop ;;
  status)
    if pid_of slurmctld >/dev/null && pid_of slurmd >/dev/null; then
      SLURM_CONF="$CONF" sinfo
    else
      log "not running"; exit 1
    fi ;;
  env) echo "export SLURM_CONF=$CONF" ;;
  *) echo "usage: $0 start|stop|status|env" >&2; exit 2 ;;
esac
