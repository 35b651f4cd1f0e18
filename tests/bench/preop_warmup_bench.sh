#!/usr/bin/env bash
# Warm-up, peak memory and restart of brainshiftd with a tumour in the preop
# (two FEM systems: the brain, and the brain with the tumour wall fixed), for
# issue 12 (results: docs/PERFORMANCE.md, section 5). For each NP: a fresh
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
# shellcheck source=daemon_bench_lib.sh
source "$(dirname "$0")/daemon_bench_lib.sh"
trap bench_cleanup EXIT
now() { date +%s.%N; }
hwm_each() { local out=""; for p in ${1//,/ }; do out+="${out:+,}$(awk '/VmHWM/ {print $2}' "/proc/$p/status")"; done; echo "[$out]"; }

echo "bench: making the tumour phantom" >&2
"$CLIENT" phantom --atlas-cache "$ATLAS_CACHE" --preset right_frontal_tumor_resection --out "$WORK/case" >/dev/null
C=$WORK/case
echo "["
first=1
for np in "${NPS[@]}"; do
  run="$WORK/np$np"
  bench_config "$run" "$np"
  start_daemon "$run" "$np"
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
  kill9_daemon "$run"
  t_restart=$(date +%s%N)
  start_daemon "$run" "$np"
  restart=$("$BENCH" --server "$SERVER" --events "$EVENTS" --labels "$C/intraop_labels.nii.gz" --restarted-at "$t_restart")
  [[ $first -eq 1 ]] || echo ","
  first=0
  printf '{"np": %s, "preset": "right_frontal_tumor_resection", "load_preop_wait_s": %s,\n "vm_hwm_kib_warm": %s, "vm_hwm_kib_after_scans": %s, "scans": %s,\n "restart": %s}\n' \
    "$np" "$warmup" "$hwm_warm" "$hwm_scans" "$SCANS" "$restart"
  grep -h "systems\|ready:" "$run/daemon.out" | tail -2 >&2 || true
  stop_daemon
done
echo "]"
