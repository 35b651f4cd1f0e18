# Shared by the daemon benchmarks (daemon_latency_bench.sh,
# preop_warmup_bench.sh); sourced after `set -euo pipefail` with BUILD set.
# Gives DAEMON CLIENT BENCH ATLAS_CACHE WORK, and the functions below; the
# caller's EXIT trap should call bench_cleanup.
SRC=$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)
DAEMON="$BUILD/server/brainshiftd"
CLIENT="$BUILD/client/brainshift"
BENCH="$BUILD/tests/bench/brainshift_daemon_latency_bench"
for bin in "$DAEMON" "$CLIENT" "$BENCH"; do
  [[ -x $bin ]] || { echo "bench: $bin is missing: build it first" >&2; exit 2; }
done
export OMPI_ALLOW_RUN_AS_ROOT=1 OMPI_ALLOW_RUN_AS_ROOT_CONFIRM=1 OPENBLAS_NUM_THREADS=1
ATLAS_CACHE="${XDG_CACHE_HOME:-$HOME/.cache}/brainshift/atlas"
WORK=$(mktemp -d /tmp/brainshift-bench.XXXXXX)
DAEMON_PID=""
DAEMON_EXTRA_ARGS=()  # appended to brainshiftd's command line (e.g. --igtl-port 0)

json_field() { sed -n "s/.*\"$1\":\"\([^\"]*\)\".*/\1/p" "$2"; }

stop_daemon() {
  [[ -n $DAEMON_PID ]] || return 0
  [[ -n ${SERVER:-} ]] && "$CLIENT" --server "$SERVER" --timeout 5 shutdown --reason "bench done" >/dev/null 2>&1 || true
  for _ in $(seq 1 150); do kill -0 "$DAEMON_PID" 2>/dev/null || break; sleep 0.2; done
  kill -TERM "$DAEMON_PID" 2>/dev/null || true
  wait "$DAEMON_PID" 2>/dev/null || true
  DAEMON_PID=""
}

# KEEP=1 keeps the work folder (logs, store, timing.jsonl) for a look.
bench_cleanup() {
  stop_daemon
  if [[ -n ${KEEP:-} ]]; then echo "bench: kept $WORK" >&2; else rm -rf "$WORK"; fi
}

# bench_config RUN_DIR NP: the default configuration with no preop at
# start-up (the benchmarks time the warm-up themselves), a store in RUN_DIR;
# sets `launch` (the daemon, under mpirun when NP > 1).
bench_config() {
  local run=$1 np=$2
  mkdir -p "$run"
  cp "$SRC/config/brainshiftd.toml" "$SRC/config/labels.toml" "$run/"
  sed -i -e "s|^atlas_cache = .*|atlas_cache = \"$ATLAS_CACHE\"|" -e "s|^store = .*|store = \"$run/store\"|" \
         -e "s|^preop = .*|preop = \"none\"|" \
         -e "s|^allow_unauthenticated_shutdown = .*|allow_unauthenticated_shutdown = true|" "$run/brainshiftd.toml"
  launch=("$DAEMON")
  if [[ $np -gt 1 ]]; then launch=(mpirun -np "$np" --oversubscribe "$DAEMON"); fi
}

# start_daemon RUN_DIR NP: launches it (logs appended in RUN_DIR) and waits
# for its ready file; sets DAEMON_PID SERVER EVENTS and pids (every rank).
start_daemon() {
  local run=$1 np=$2
  rm -f "$run/ready.json"
  "${launch[@]}" --config "$run/brainshiftd.toml" --endpoint 'tcp://127.0.0.1:*' --events 'tcp://127.0.0.1:*' \
    --ready-file "$run/ready.json" "${DAEMON_EXTRA_ARGS[@]}" >>"$run/daemon.out" 2>>"$run/daemon.log" &
  DAEMON_PID=$!
  for _ in $(seq 1 3000); do [[ -f $run/ready.json ]] && break; sleep 0.01; done
  [[ -f $run/ready.json ]] || { echo "bench: daemon (np $np) did not start; see $run/daemon.log" >&2; exit 1; }
  SERVER=$(json_field endpoint "$run/ready.json")
  EVENTS=$(json_field events "$run/ready.json")
  if [[ $np -gt 1 ]]; then pids=$(pgrep -d, -P "$DAEMON_PID" -x brainshiftd || true); else pids=$DAEMON_PID; fi
}

# kill9_daemon RUN_DIR: SIGKILL of rank 0 (mpirun then ends the job).
kill9_daemon() {
  kill -9 "$(sed -n 's/.*"pid":\([0-9]*\).*/\1/p' "$1/ready.json")"
  wait "$DAEMON_PID" 2>/dev/null || true
  DAEMON_PID=""
}
