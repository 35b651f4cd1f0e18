#!/usr/bin/env bash
# The daemon latency benchmark of issues 4 and 12 (results: docs/PERFORMANCE.md,
# section 4). For each NP: starts brainshiftd on a fresh store with no preop,
# times preop.load of the default atlas (published mesh size), then SCANS times
# runs the user's command `brainshift push --labels L --image I --wait` on a
# `brainshift phantom` scan (256x256x60 intraop grid) once the daemon is idle,
# timed from the command's start to its exit, beside the daemon's stage table;
# reports VmRSS and VmHWM (peak) of every rank after the scans; then pushes
# RESTART_SCANS (default 2) scans without waiting, kill -9s the daemon and
# times the restart from the stored preop: launch -> ready -> all processed.
# Prints one JSON object per NP, as a JSON array.
# Usage: [PRESET=name] [DIRECT=1] [KEEP=1] tests/bench/daemon_latency_bench.sh BUILD_DIR [SCANS] [NP...]
#        (default 20 scans, NP 1 2, phantom preset left_frontal_sinking_12mm;
#        DIRECT=1: the benchmark pushes itself, scan.push sent -> scan.done)
set -euo pipefail
BUILD=$(cd "${1:?usage: $0 BUILD_DIR [SCANS] [NP...]}" && pwd)
SCANS=${2:-20}
shift $(( $# >= 2 ? 2 : 1 ))
NPS=("$@")
[[ ${#NPS[@]} -gt 0 ]] || NPS=(1 2)
SRC=$(cd "$(dirname "$0")/../.." && pwd)
DAEMON="$BUILD/server/brainshiftd"
CLIENT="$BUILD/client/brainshift"
BENCH="$BUILD/tests/bench/brainshift_daemon_latency_bench"
for bin in "$DAEMON" "$CLIENT" "$BENCH"; do
  [[ -x $bin ]] || { echo "bench: $bin is missing: build it first" >&2; exit 2; }
done
export OMPI_ALLOW_RUN_AS_ROOT=1 OMPI_ALLOW_RUN_AS_ROOT_CONFIRM=1 OPENBLAS_NUM_THREADS=1
ATLAS_CACHE="${XDG_CACHE_HOME:-$HOME/.cache}/brainshift/atlas"
WORK=$(mktemp -d /tmp/brainshift-latency.XXXXXX)
DAEMON_PID=""

stop_daemon() {
  [[ -n $DAEMON_PID ]] || return 0
  [[ -n ${SERVER:-} ]] && "$CLIENT" --server "$SERVER" --timeout 5 shutdown --reason "bench done" >/dev/null 2>&1 || true
  for _ in $(seq 1 150); do kill -0 "$DAEMON_PID" 2>/dev/null || break; sleep 0.2; done
  kill -TERM "$DAEMON_PID" 2>/dev/null || true
  wait "$DAEMON_PID" 2>/dev/null || true
  DAEMON_PID=""
}
trap 'stop_daemon; [[ -n ${KEEP:-} ]] && echo "bench: kept $WORK" >&2 || rm -rf "$WORK"' EXIT

echo "bench: making the phantom scan" >&2
"$CLIENT" phantom --atlas-cache "$ATLAS_CACHE" --preset "${PRESET:-left_frontal_sinking_12mm}" --out "$WORK/phantom" >/dev/null

json_field() { sed -n "s/.*\"$1\":\"\([^\"]*\)\".*/\1/p" "$2"; }
client_args=(--client "$CLIENT")
[[ -n ${DIRECT:-} ]] && client_args=()
echo "[" 
first=1
for np in "${NPS[@]}"; do
  run="$WORK/np$np"
  mkdir -p "$run"
  cp "$SRC/config/brainshiftd.toml" "$SRC/config/labels.toml" "$run/"
  # No preop at start-up: the benchmark times preop.load itself.
  sed -i -e "s|^atlas_cache = .*|atlas_cache = \"$ATLAS_CACHE\"|" -e "s|^store = .*|store = \"$run/store\"|" \
         -e "s|^preop = .*|preop = \"none\"|" \
         -e "s|^allow_unauthenticated_shutdown = .*|allow_unauthenticated_shutdown = true|" "$run/brainshiftd.toml"
  launch=("$DAEMON")
  [[ $np -gt 1 ]] && launch=(mpirun -np "$np" --oversubscribe "$DAEMON")
  "${launch[@]}" --config "$run/brainshiftd.toml" --endpoint 'tcp://127.0.0.1:*' --events 'tcp://127.0.0.1:*' \
    --ready-file "$run/ready.json" >"$run/daemon.out" 2>"$run/daemon.log" &
  DAEMON_PID=$!
  for _ in $(seq 1 300); do [[ -f $run/ready.json ]] && break; sleep 0.1; done
  [[ -f $run/ready.json ]] || { echo "bench: daemon (np $np) did not start; see $run/daemon.log" >&2; exit 1; }
  SERVER=$(json_field endpoint "$run/ready.json")
  EVENTS=$(json_field events "$run/ready.json")
  # Every rank: the brainshiftd processes under mpirun, or the daemon itself.
  if [[ $np -gt 1 ]]; then
    pids=$(pgrep -d, -P "$DAEMON_PID" -x brainshiftd || true)
  else
    pids=$DAEMON_PID
  fi
  echo "bench: np $np, daemon pids $pids" >&2
  [[ $first -eq 1 ]] || echo ","
  first=0
  "$BENCH" --server "$SERVER" --events "$EVENTS" --labels "$WORK/phantom/intraop_labels.nii.gz" \
    --image "$WORK/phantom/intraop_t1.nii.gz" --scans "$SCANS" --load-preop --pids "$pids" \
    "${client_args[@]}" |
    sed "1s/^{/{\n  \"np\": $np,/"
  # Restart after kill -9 with the preop in the store and RESTART_SCANS
  # acknowledged scans not yet processed: launch -> ready, -> all processed.
  for _ in $(seq 1 "${RESTART_SCANS:-2}"); do
    "$CLIENT" --server "$SERVER" push --labels "$WORK/phantom/intraop_labels.nii.gz" \
      --image "$WORK/phantom/intraop_t1.nii.gz" >/dev/null
  done
  kill -9 "$(sed -n 's/.*"pid":\([0-9]*\).*/\1/p' "$run/ready.json")"
  wait "$DAEMON_PID" 2>/dev/null || true
  rm -f "$run/ready.json"
  t_restart=$(date +%s%N)
  "${launch[@]}" --config "$run/brainshiftd.toml" --endpoint 'tcp://127.0.0.1:*' --events 'tcp://127.0.0.1:*' \
    --ready-file "$run/ready.json" >>"$run/daemon.out" 2>>"$run/daemon.log" &
  DAEMON_PID=$!
  for _ in $(seq 1 3000); do [[ -f $run/ready.json ]] && break; sleep 0.01; done
  SERVER=$(json_field endpoint "$run/ready.json")
  EVENTS=$(json_field events "$run/ready.json")
  echo ","
  "$BENCH" --server "$SERVER" --events "$EVENTS" --labels "$WORK/phantom/intraop_labels.nii.gz" \
    --restarted-at "$t_restart" | sed "1s/^{/{\n  \"np\": $np, \"restart_after_kill9\": true,/"
  stop_daemon
done
echo "]"
