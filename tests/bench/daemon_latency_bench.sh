#!/usr/bin/env bash
# The daemon latency benchmark of issues 4 and 12 (results: docs/PERFORMANCE.md,
# section 5). For each NP: starts brainshiftd on a fresh store with no preop,
# times preop.load of the default atlas (published mesh size), then SCANS times
# runs the user's command `brainshift push --labels L --image I --wait` on a
# `brainshift phantom` scan (256x256x60 intraop grid) once the daemon is idle,
# timed from the command's start to its exit, beside the daemon's stage table;
# reports VmRSS and VmHWM (peak) of every rank after the scans; then pushes
# RESTART_SCANS (default 2) scans without waiting, kill -9s the daemon and
# times the restart from the stored preop: launch -> ready -> all processed.
# Prints one JSON object per NP, as a JSON array.
# Usage: [PRESET=name] [DIRECT=1] [KEEP=1] [IGTL=1] [IMAGE_ONLY=1] tests/bench/daemon_latency_bench.sh BUILD_DIR [SCANS] [NP...]
#        (default 20 scans, NP 1 2, phantom preset left_frontal_sinking_12mm;
#        DIRECT=1: the benchmark pushes itself, scan.push sent -> scan.done;
#        IGTL=1: the OpenIGTLink gateway on, with one receiver connected
#        (brainshift_igtl_receive_bench); its JSON goes to stderr;
#        IMAGE_ONLY=1: the scans are pushed as the image alone, the daemon
#        segments them (PROTOCOL.md 5.3))
set -euo pipefail
BUILD=$(cd "${1:?usage: $0 BUILD_DIR [SCANS] [NP...]}" && pwd)
SCANS=${2:-20}
shift $(( $# >= 2 ? 2 : 1 ))
NPS=("$@")
[[ ${#NPS[@]} -gt 0 ]] || NPS=(1 2)
# shellcheck source=daemon_bench_lib.sh
source "$(dirname "$0")/daemon_bench_lib.sh"
trap bench_cleanup EXIT

echo "bench: making the phantom scan" >&2
"$CLIENT" phantom --atlas-cache "$ATLAS_CACHE" --preset "${PRESET:-left_frontal_sinking_12mm}" --out "$WORK/phantom" >/dev/null

labels_args=(--labels "$WORK/phantom/intraop_labels.nii.gz")
[[ ${IMAGE_ONLY:-0} == 1 ]] && labels_args=()
client_args=(--client "$CLIENT")
[[ -n ${DIRECT:-} ]] && client_args=()
echo "[" 
first=1
for np in "${NPS[@]}"; do
  run="$WORK/np$np"
  bench_config "$run" "$np"
  DAEMON_EXTRA_ARGS=()
  [[ ${IGTL:-0} == 1 ]] && DAEMON_EXTRA_ARGS=(--igtl-port 0)
  start_daemon "$run" "$np"
  echo "bench: np $np, daemon pids $pids" >&2
  RECEIVER_PID=""
  if [[ ${IGTL:-0} == 1 ]]; then
    port=$(sed -n 's/.*"igtl_port":\([0-9]*\).*/\1/p' "$run/ready.json")
    "$BUILD/tests/bench/brainshift_igtl_receive_bench" --port "$port" --results "$SCANS" >&2 &
    RECEIVER_PID=$!
  fi
  [[ $first -eq 1 ]] || echo ","
  first=0
  "$BENCH" --server "$SERVER" --events "$EVENTS" "${labels_args[@]}" \
    --image "$WORK/phantom/intraop_t1.nii.gz" --scans "$SCANS" --load-preop --pids "$pids" \
    "${client_args[@]}" |
    sed "1s/^{/{\n  \"np\": $np,/"
  [[ -n $RECEIVER_PID ]] && wait "$RECEIVER_PID"
  # Restart after kill -9 with the preop in the store and RESTART_SCANS
  # acknowledged scans not yet processed: launch -> ready, -> all processed.
  for _ in $(seq 1 "${RESTART_SCANS:-2}"); do
    "$CLIENT" --server "$SERVER" push "${labels_args[@]}" \
      --image "$WORK/phantom/intraop_t1.nii.gz" >/dev/null
  done
  kill9_daemon "$run"
  t_restart=$(date +%s%N)
  start_daemon "$run" "$np"
  echo ","
  "$BENCH" --server "$SERVER" --events "$EVENTS" --image "$WORK/phantom/intraop_t1.nii.gz" \
    --restarted-at "$t_restart" | sed "1s/^{/{\n  \"np\": $np, \"restart_after_kill9\": true,/"
  stop_daemon
done
echo "]"
