#!/usr/bin/env bash
# The compose topology as plain processes on one machine: a dask scheduler, two workers, and the server
# sending the chunked work of its jobs to them (--scheduler). Used by the tests and for trying a facility set-up without containers.
#
#   deploy/local.sh start DATA_ROOT     start everything; prints "server HOST:PORT" and "scheduler tcp://..."
#   deploy/local.sh stop DATA_ROOT      SIGTERM the server (it drains its jobs), then the workers and scheduler
#   deploy/local.sh status DATA_ROOT    which processes run
#
# Environment: PYTHON (default .venv/bin/python beside this repo, else python3), UNWIND_PORT (default 50051;
# 0: any free port), DASK_PORT (default 8786; 0: any free port), UNWIND_ARGS (more `serve` options, e.g.
# "--tokens /etc/unwind/tokens"), WORKER_THREADS (default 1). Logs and pid files go to DATA_ROOT/.local-run/.
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
repo="$(dirname "$here")"
PYTHON="${PYTHON:-$( [ -x "$repo/.venv/bin/python" ] && echo "$repo/.venv/bin/python" || command -v python3 )}"
cmd="${1:-}"; root="${2:-}"
[ -n "$cmd" ] && [ -n "$root" ] || { sed -n '2,12p' "$0" >&2; exit 2; }
mkdir -p "$root"
run="$root/.local-run"
mkdir -p "$run"

wait_for_line() {  # file pattern seconds
  local i=0
  while ! grep -qE "$2" "$1" 2>/dev/null; do
    sleep 0.2; i=$((i + 1))
    if [ "$i" -gt $(( $3 * 5 )) ]; then echo "local.sh: timed out waiting for '$2' in $1" >&2; tail -20 "$1" >&2; exit 1; fi
  done
}

case "$cmd" in
start)
  "$PYTHON" -m distributed.cli.dask_scheduler --host 127.0.0.1 --port "${DASK_PORT:-8786}" --no-dashboard \
    >"$run/scheduler.log" 2>&1 &
  echo $! >"$run/scheduler.pid"
  wait_for_line "$run/scheduler.log" "Scheduler at:" 60
  sched="$(grep -oE 'tcp://[0-9.]+:[0-9]+' "$run/scheduler.log" | head -1)"
  echo "$sched" >"$run/scheduler.address"
  for w in 1 2; do
    "$PYTHON" -m distributed.cli.dask_worker "$sched" --host 127.0.0.1 --nthreads "${WORKER_THREADS:-1}" \
      --nworkers 1 --no-nanny --no-dashboard --name "worker-$w" --local-directory "$run/worker-$w" \
      >"$run/worker-$w.log" 2>&1 &
    echo $! >"$run/worker-$w.pid"
  done
  for w in 1 2; do wait_for_line "$run/worker-$w.log" "Registered to" 60; done
  # shellcheck disable=SC2086
  "$PYTHON" -u -m napari_unwind.cli serve --data-root "$root" --port "${UNWIND_PORT:-50051}" \
    --scheduler "$sched" ${UNWIND_ARGS:-} >"$run/server.out" 2>"$run/server.log" &
  echo $! >"$run/server.pid"
  wait_for_line "$run/server.out" "listening on" 120
  echo "server $(grep -oE 'listening on [^ ]+' "$run/server.out" | cut -d' ' -f3)"
  echo "scheduler $sched"
  ;;
stop)
  for p in server worker-1 worker-2 scheduler; do
    if [ -f "$run/$p.pid" ]; then
      pid="$(cat "$run/$p.pid")"
      if kill -0 "$pid" 2>/dev/null; then
        kill -TERM "$pid" 2>/dev/null || true
        for _ in $(seq 1 150); do kill -0 "$pid" 2>/dev/null || break; sleep 0.2; done
        kill -KILL "$pid" 2>/dev/null || true
      fi
      rm -f "$run/$p.pid"
    fi
  done
  ;;
status)
  for p in scheduler worker-1 worker-2 server; do
    if [ -f "$run/$p.pid" ] && kill -0 "$(cat "$run/$p.pid")" 2>/dev/null; then
      echo "$p running (pid $(cat "$run/$p.pid"))"
    else
      echo "$p stopped"
    fi
  done
  ;;
*)
  sed -n '2,12p' "$0" >&2; exit 2 ;;
esac
