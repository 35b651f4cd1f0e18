#!/usr/bin/env bash
# Warm-up, peak memory and restart of brainshiftd with a tumour in the preop
# (two FEM systems: the brain, and the brain with the tumour wall fixed), for
# issue 12 (results: docs/PERFORMANCE.md, section 4). For each NP: a fresh
# store; `brainshift load-preop --image --labels --wait` of the
# right_frontal_tumor_resection phantom's preop (meshing included), timed from
# the command's start to its exit; VmHWM (peak) of every rank when warm and
# after SCANS `brainshift push --wait` scans; then RESTART_SCANS scans pushed
# without waiting, kill -9, and the restart from the stored preop timed to
# ready and to every acknowledged scan processed. One JSON object per NP.
# Usage: tests/bench/preop_warmup_bench.sh BUILD_DIR [SCANS] [NP...]   (default 3 scans, NP 1 2)
set -euo pipefail
BUILD=$(cd "${1:?usage: $0 BUILD_DIR [SCANS] [NP...]}" && pwd)
SCANS=${2:-3}
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
WORK=$(mktemp -d /tmp/brainshift-warmup.XXXXXX)
DAEMON_PID=""
stop_daemon() {
  [[ -n $DAEMON_PID ]] || return 0
  "$CLIENT" --server "$SERVER" --timeout 5 shutdown --reason "bench done" >/dev/null 2>&1 || true
  for _ in $(seq 1 150); do kill -0 "$DAEMON_PID" 2>/dev/null || break; sleep 0.2; done
  kill -TERM "$DAEMON_PID" 2>/dev/null || true
  wait "$DAEMON_PID" 2>/dev/null || true
  DAEMON_PID=""
}
trap 'stop_daemon; rm -rf "$WORK"' EXIT
now() { date +%s.%N; }
json_field() { sed -n "s/.*\"$1\":\"\([^\"]*\)\".*/\1/p" "$2"; }
hwm_kib() { local total=0; for p in ${1//,/ }; do total=$((total + $(awk '/VmHWM/ {print $2}' "/proc/$p/status"))); done; echo "$total"; }
hwm_each() { local out=""; for p in ${1//,/ }; do out+="${out:+,}$(awk '/VmHWM/ {print $2}' "/proc/$p/status")"; done; echo "[$out]"; }

echo "bench: making the tumour phantom" >&2
"$CLIENT" phantom --atlas-cache "$ATLAS_CACHE" --preset right_frontal_tumor_resection --out "$WORK/case" >/dev/null
C=$WORK/case
echo "["
first=1
for np in "${NPS[@]}"; do
  run="$WORK/np$np"
  mkdir -p "$run"
  cp "$SRC/config/brainshiftd.toml" "$SRC/config/labels.toml" "$run/"
  sed -i -e "s|^atlas_cache = .*|atlas_cache = \"$ATLAS_CACHE\"|" -e "s|^store = .*|store = \"$run/store\"|" \
         -e "s|^preop = .*|preop = \"none\"|" \
         -e "s|^allow_unauthenticated_shutdown = .*|allow_unauthenticated_shutdown = true|" "$run/brainshiftd.toml"
  launch=("$DAEMON")
  [[ $np -gt 1 ]] && launch=(mpirun -np "$np" --oversubscribe "$DAEMON")
  start_daemon() {
    rm -f "$run/ready.json"
    "${launch[@]}" --config "$run/brainshiftd.toml" --endpoint 'tcp://127.0.0.1:*' --events 'tcp://127.0.0.1:*' \
      --ready-file "$run/ready.json" >>"$run/daemon.out" 2>>"$run/daemon.log" &
    DAEMON_PID=$!
    for _ in $(seq 1 3000); do [[ -f $run/ready.json ]] && break; sleep 0.01; done
    [[ -f $run/ready.json ]] || { echo "bench: daemon (np $np) did not start; see $run/daemon.log" >&2; exit 1; }
    SERVER=$(json_field endpoint "$run/ready.json")
    EVENTS=$(json_field events "$run/ready.json")
    if [[ $np -gt 1 ]]; then pids=$(pgrep -d, -P "$DAEMON_PID" -x brainshiftd || true); else pids=$DAEMON_PID; fi
  }
  start_daemon
  t0=$(now)
  "$CLIENT" --server "$SERVER" --events "$EVENTS" load-preop --image "$C/preop_t1.nii.gz" \
    --labels "$C/preop_labels.nii.gz" --wait >/dev/null 2>"$run/load.err"
  warmup=$(awk -v a="$(now)" -v b="$t0" 'BEGIN { printf "%.3f", a - b }')
  hwm_warm=$(hwm_each "$pids")
  for _ in $(seq 1 "$SCANS"); do
    "$CLIENT" --server "$SERVER" --events "$EVENTS" push --labels "$C/intraop_labels.nii.gz" \
      --image "$C/intraop_t1.nii.gz" --wait >/dev/null 2>>"$run/push.err"
  done
  sleep 3  # the deferred outputs of the last scan
  hwm_scans=$(hwm_each "$pids")
  for _ in $(seq 1 "${RESTART_SCANS:-2}"); do
    "$CLIENT" --server "$SERVER" push --labels "$C/intraop_labels.nii.gz" --image "$C/intraop_t1.nii.gz" >/dev/null
  done
  kill -9 "$(sed -n 's/.*"pid":\([0-9]*\).*/\1/p' "$run/ready.json")"
  wait "$DAEMON_PID" 2>/dev/null || true
  t_restart=$(date +%s%N)
  start_daemon
  restart=$("$BENCH" --server "$SERVER" --events "$EVENTS" --labels "$C/intraop_labels.nii.gz" --restarted-at "$t_restart")
  [[ $first -eq 1 ]] || echo ","
  first=0
  printf '{"np": %s, "preset": "right_frontal_tumor_resection", "load_preop_wait_s": %s,\n "vm_hwm_kib_warm": %s, "vm_hwm_kib_after_scans": %s, "scans": %s,\n "restart": %s}\n' \
    "$np" "$warmup" "$hwm_warm" "$hwm_scans" "$SCANS" "$restart"
  grep -h "systems\|ready:" "$run/daemon.out" | tail -2 >&2 || true
  stop_daemon
done
echo "]"
