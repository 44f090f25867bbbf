#!/usr/bin/env bash
# One MLflow tracking server for the runs of many jobs, e.g. SLURM jobs on several nodes
# (docs/tracking.md, "One tracking server for many jobs"):
#   bash scripts/mlflow_server.sh start    start it in the background, wait until /health answers,
#                                          print the tracking URI the jobs are to use
#   bash scripts/mlflow_server.sh stop     stop it (the process group of the pid in its pid file)
#   bash scripts/mlflow_server.sh status   say whether it runs (exit 0) or not (exit 1)
# Then, in every job: export MLFLOW_TRACKING_URI=<the URI printed>, or tracking.uri=<it>.
#
# The server alone opens its database (a SQLite file in its folder) and serves the artifacts
# (`--artifacts-destination`, proxied: runs record `mlflow-artifacts:/` locations), so a job
# on another node needs only the URI, no shared path. Uses .venv/bin/mlflow when present,
# else the mlflow on PATH.
#
# Environment:
#   PARTY_MLFLOW_HOST     interface to bind (default 127.0.0.1: this machine only); 0.0.0.0 (or the
#                         node's address) for jobs on other nodes, which then reach it by this
#                         node's host name; anyone who can reach the port can read and write runs
#   PARTY_MLFLOW_PORT     port (default 5000)
#   PARTY_MLFLOW_DIR      the server's folder (default mlruns-server/ in the project, git-ignored):
#                         mlflow.db, artifacts/, server.log, server.pid; relative to the project
#   PARTY_MLFLOW_WORKERS  server worker processes (default 4, see below)
#   PARTY_MLFLOW_WAIT     seconds to wait for /health at start (default 120)
#   PARTY_MLFLOW_JOBS     true: also run mlflow's job runner (GenAI jobs; default false)
#   PARTY_MLFLOW_ALLOWED_HOSTS  Host headers the server accepts (mlflow's --allowed-hosts); default:
#                         loopback and private addresses, plus this node's names when bound beyond it
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$PWD
HOST=${PARTY_MLFLOW_HOST:-127.0.0.1}
PORT=${PARTY_MLFLOW_PORT:-5000}
DIR=${PARTY_MLFLOW_DIR:-mlruns-server}
[[ "$DIR" = /* ]] || DIR="$ROOT/$DIR"
# Workers: mlflow's default of 4 processes. Each opens the SQLite file with its own pool of 15
# connections (5 + 10 overflow); SQLite lets one writer in at a time and the others wait on its
# lock (up to 5 s) rather than fail, and the client retries a 5xx. Under concurrent clients (up to
# 32 threads logging batches and searching runs, client retries off) 4 workers answered every
# request and never "database is locked"; 1 worker, not 4, was what failed: its one pool ran dry
# ("QueuePool limit of size 5 overflow 10 reached", a 400 the client does not retry). More jobs
# than that: more workers, or a larger pool (MLFLOW_SQLALCHEMYSTORE_POOL_SIZE).
WORKERS=${PARTY_MLFLOW_WORKERS:-4}
WAIT=${PARTY_MLFLOW_WAIT:-120}
PIDFILE="$DIR/server.pid"
LOG="$DIR/server.log"
cmd=${1:-}

usage() { echo "usage: bash scripts/mlflow_server.sh start|stop|status" >&2; exit 2; }
[[ "$PORT" =~ ^[0-9]+$ ]] || { echo "mlflow_server: PARTY_MLFLOW_PORT=$PORT is not a port number" >&2; exit 2; }

# the host name clients use: the bind address itself, or this node's name for a wildcard bind
case "$HOST" in
  0.0.0.0|::|"[::]") CLIENT_HOST=$(hostname -f 2>/dev/null || hostname) ;;
  *) CLIENT_HOST=$HOST ;;
esac
[[ "$CLIENT_HOST" == *:* && "$CLIENT_HOST" != \[* ]] && CLIENT_HOST="[$CLIENT_HOST]"   # IPv6 literal
URI="http://$CLIENT_HOST:$PORT"
# where this script probes /health: loopback for a wildcard bind
case "$HOST" in
  0.0.0.0) PROBE=127.0.0.1 ;;
  ::|"[::]") PROBE="[::1]" ;;
  *) PROBE=$CLIENT_HOST ;;
esac

running_pid() {
  # the pid in the pid file when that process is alive and is an mlflow server; else nothing
  [ -f "$PIDFILE" ] || return 1
  local pid
  pid=$(cat "$PIDFILE" 2>/dev/null || true)
  [[ "$pid" =~ ^[0-9]+$ ]] || return 1
  kill -0 "$pid" 2>/dev/null || return 1
  tr '\0' ' ' < "/proc/$pid/cmdline" 2>/dev/null | grep -q "mlflow" || return 1
  echo "$pid"
}

healthy() {
  curl -sf --max-time 3 "http://$PROBE:$PORT/health" >/dev/null 2>&1
}

port_taken() {
  (exec 3<>"/dev/tcp/${PROBE//[\[\]]/}/$PORT") 2>/dev/null
}

log_tail() {
  echo "--- last lines of $LOG ---" >&2
  tail -n 30 "$LOG" >&2 2>/dev/null || true
}

print_uri() {
  echo "tracking URI: $URI"
  echo "  export MLFLOW_TRACKING_URI=$URI     # or: party <stage> tracking.uri=$URI"
}

case "$cmd" in
  start)
    MLFLOW=.venv/bin/mlflow
    [ -x "$MLFLOW" ] || MLFLOW=$(command -v mlflow || true)
    if [ -z "$MLFLOW" ]; then
      echo "mlflow_server: mlflow not found: run bash scripts/setup.sh (or pip install mlflow)" >&2
      exit 1
    fi
    command -v curl >/dev/null || { echo "mlflow_server: curl not found (it probes /health)" >&2; exit 1; }
    if pid=$(running_pid); then
      echo "mlflow server already running (pid $pid, $DIR)"
      print_uri
      exit 0
    fi
    if port_taken; then
      echo "mlflow_server: port $PORT on $PROBE is taken by another process; set PARTY_MLFLOW_PORT" >&2
      exit 1
    fi
    mkdir -p "$DIR/artifacts"
    if [ -n "${PARTY_MLFLOW_ALLOWED_HOSTS:-}" ]; then
      ALLOWED=$PARTY_MLFLOW_ALLOWED_HOSTS
    else   # mlflow's default (loopback, private addresses) and this node's names for other nodes
      ALLOWED="localhost,localhost:*,127.0.0.1,127.0.0.1:*,[[]::1]:*,10.*,192.168.*,fc00:*,fd00:*"
      for i in $(seq 16 31); do ALLOWED+=",172.$i.*"; done
      for name in "$HOST" "$(hostname)" "$(hostname -f 2>/dev/null || true)"; do
        [ -n "$name" ] && [ "$name" != 0.0.0.0 ] && [ "$name" != "::" ] && ALLOWED+=",$name,$name:*"
      done
    fi
    # setsid: the server (and the uvicorn processes it starts) in a process group of its own, so
    # `stop` ends all of them and a Ctrl-C in this terminal none of them
    # mlflow's job runner (GenAI scorers and periodic tasks: eight more processes on the same
    # SQLite file) is not used by party; PARTY_MLFLOW_JOBS=true keeps it
    MLFLOW_SERVER_ENABLE_JOB_EXECUTION=${PARTY_MLFLOW_JOBS:-false} setsid "$MLFLOW" server \
      --backend-store-uri "sqlite:///$DIR/mlflow.db" \
      --serve-artifacts --artifacts-destination "$DIR/artifacts" \
      --default-artifact-root mlflow-artifacts:/ \
      --host "$HOST" --port "$PORT" --workers "$WORKERS" \
      --allowed-hosts "$ALLOWED" \
      >"$LOG" 2>&1 < /dev/null &
    pid=$!
    echo "$pid" > "$PIDFILE"
    waited=0
    until healthy; do
      if ! kill -0 "$pid" 2>/dev/null; then
        echo "mlflow_server: the server exited before answering on $PROBE:$PORT" >&2
        log_tail
        rm -f "$PIDFILE"
        exit 1
      fi
      if (( waited >= WAIT )); then
        echo "mlflow_server: no answer from http://$PROBE:$PORT/health after ${WAIT}s (PARTY_MLFLOW_WAIT);" \
             "stopping it" >&2
        log_tail
        kill -TERM -- "-$pid" 2>/dev/null || true
        rm -f "$PIDFILE"
        exit 1
      fi
      sleep 1
      waited=$((waited + 1))
    done
    echo "mlflow server running (pid $pid, $WORKERS worker(s), store $DIR/mlflow.db, artifacts $DIR/artifacts," \
         "log $LOG)"
    print_uri
    ;;
  stop)
    if ! pid=$(running_pid); then
      echo "mlflow server not running ($PIDFILE names no live mlflow process)"
      rm -f "$PIDFILE"
      exit 0
    fi
    kill -TERM -- "-$pid" 2>/dev/null || kill -TERM "$pid"
    for _ in $(seq 1 30); do
      kill -0 "$pid" 2>/dev/null || break
      sleep 1
    done
    if kill -0 "$pid" 2>/dev/null; then
      echo "mlflow server (pid $pid) still running 30 s after SIGTERM; sending SIGKILL" >&2
      kill -KILL -- "-$pid" 2>/dev/null || kill -KILL "$pid"
    fi
    rm -f "$PIDFILE"
    echo "mlflow server stopped (pid $pid)"
    ;;
  status)
    if pid=$(running_pid); then
      if healthy; then
        echo "mlflow server running (pid $pid, $DIR), answering at $URI"
      else
        echo "mlflow server process running (pid $pid, $DIR) but http://$PROBE:$PORT/health does not answer"
      fi
      exit 0
    fi
    echo "mlflow server not running ($DIR)"
    exit 1
    ;;
  *) usage ;;
esac
