#!/usr/bin/env bash
# The operating-room demo, end to end on this machine:
#   1. start brainshiftd on loopback with the default Colin27 atlas,
#   2. wait until the atlas, mesh and factorisation are warm,
#   3. make a phantom intraop scan (`brainshift phantom`) as the scanner would,
#   4. push it and wait for the result,
#   5. pull the field and models as the visualisation station would, with a
#      3D Slicer scene of them (scene.mrml),
#   6. pull report.png, print the timing table, write everything to OUT_DIR,
#   7. stop the daemon (also on any error or Ctrl-C: see the trap).
# Usage: tests/demo.sh BUILD_DIR OUT_DIR [PRESET]
# DEMO_DICOM=1: the scanner's T1 is a DICOM series (the phantom written with
# DCMTK, OUT_DIR/phantom/intraop_dicom), pushed with `push --dicom`.
set -euo pipefail

if [[ $# -lt 2 ]]; then
  echo "usage: $0 BUILD_DIR OUT_DIR [PRESET]" >&2
  exit 2
fi
BUILD=$(cd "$1" && pwd)
mkdir -p "$2"
OUT=$(cd "$2" && pwd)
PRESET=${3:-left_frontal_sinking_12mm}
SRC=$(cd "$(dirname "$0")/.." && pwd)
DAEMON="$BUILD/server/brainshiftd"
CLIENT="$BUILD/client/brainshift"
for bin in "$DAEMON" "$CLIENT"; do
  [[ -x $bin ]] || { echo "demo: $bin is missing: build the project first" >&2; exit 2; }
done

WORK="$OUT/daemon"
STORE="$WORK/store"
ATLAS_CACHE="${XDG_CACHE_HOME:-$HOME/.cache}/brainshift/atlas"
rm -rf "$WORK" "$OUT/result" "$OUT/phantom"
mkdir -p "$WORK"

# The shipped configuration, with the atlas cached once per user (building it
# takes a while) and a store of its own for this demo.
cp "$SRC/config/brainshiftd.toml" "$SRC/config/labels.toml" "$WORK/"
sed -i -e "s|^atlas_cache = .*|atlas_cache = \"$ATLAS_CACHE\"|" \
       -e "s|^store = .*|store = \"$STORE\"|" \
       -e "s|^allow_unauthenticated_shutdown = .*|allow_unauthenticated_shutdown = true|" "$WORK/brainshiftd.toml"

"$DAEMON" --config "$WORK/brainshiftd.toml" --endpoint 'tcp://127.0.0.1:*' --events 'tcp://127.0.0.1:*' \
  --ready-file "$WORK/ready.json" >"$WORK/daemon.out" 2>"$WORK/daemon.log" &
DAEMON_PID=$!
WATCH_PID=""

stop_daemon() {
  local rc=$?
  [[ -n $WATCH_PID ]] && kill "$WATCH_PID" 2>/dev/null || true
  if kill -0 "$DAEMON_PID" 2>/dev/null; then
    echo "demo: stopping brainshiftd" >&2
    [[ -n ${SERVER:-} ]] && "$CLIENT" --server "$SERVER" --timeout 5 shutdown --reason "demo finished" 2>/dev/null || true
    for _ in $(seq 1 100); do kill -0 "$DAEMON_PID" 2>/dev/null || break; sleep 0.2; done
    kill -TERM "$DAEMON_PID" 2>/dev/null || true
    for _ in $(seq 1 100); do kill -0 "$DAEMON_PID" 2>/dev/null || break; sleep 0.2; done
    kill -KILL "$DAEMON_PID" 2>/dev/null || true
  fi
  wait "$DAEMON_PID" 2>/dev/null || true
  if [[ $rc -ne 0 ]]; then
    echo "demo: FAILED (exit $rc); daemon log: $WORK/daemon.log" >&2
    tail -n 20 "$WORK/daemon.log" >&2 || true
  fi
  exit $rc
}
trap stop_daemon EXIT
trap 'exit 130' INT TERM

for _ in $(seq 1 300); do
  [[ -f $WORK/ready.json ]] && break
  kill -0 "$DAEMON_PID" 2>/dev/null || { echo "demo: brainshiftd exited" >&2; exit 1; }
  sleep 0.1
done
[[ -f $WORK/ready.json ]] || { echo "demo: brainshiftd did not bind its sockets" >&2; exit 1; }
json_field() { sed -n "s/.*\"$1\":\"\([^\"]*\)\".*/\1/p" "$2"; }
SERVER=$(json_field endpoint "$WORK/ready.json")
EVENTS=$(json_field events "$WORK/ready.json")
bs() { "$CLIENT" --server "$SERVER" --events "$EVENTS" "$@"; }
echo "demo: brainshiftd listening on $SERVER (events $EVENTS)"

# Everything published from now on, one JSON line per event.
"$CLIENT" --events "$EVENTS" watch --json >"$OUT/events.jsonl" 2>/dev/null &
WATCH_PID=$!

echo "demo: warming up the default atlas (first run builds and caches it)..."
start=$(date +%s)
while :; do
  state=$(bs --timeout 5 status --json | sed -n 's/.*"state":"\([a-z_]*\)".*/\1/p')
  [[ $state == ready ]] && break
  if [[ $state == idle ]]; then echo "demo: the warm-up failed" >&2; bs status >&2 || true; exit 1; fi
  (( $(date +%s) - start > 1800 )) && { echo "demo: warm-up timed out" >&2; exit 1; }
  sleep 1
done
echo "demo: ready after $(( $(date +%s) - start )) s"
bs status

echo "demo: making a phantom intraop scan ($PRESET)"
DICOM_FLAG=(); [[ ${DEMO_DICOM:-0} == 1 ]] && DICOM_FLAG=(--dicom)
"$CLIENT" phantom --atlas-cache "$ATLAS_CACHE" --preset "$PRESET" --out "$OUT/phantom" "${DICOM_FLAG[@]}" >/dev/null

echo "demo: pushing it as the scanner would"
IMAGE=(--image "$OUT/phantom/intraop_t1.nii.gz")
if [[ ${DEMO_DICOM:-0} == 1 ]]; then
  IMAGE=(--dicom "$OUT/phantom/intraop_dicom")
  echo "demo: the intraop T1 is the DICOM series $OUT/phantom/intraop_dicom ($(ls "$OUT/phantom/intraop_dicom" | wc -l) slices)"
fi
SCAN=$(bs push --labels "$OUT/phantom/intraop_labels.nii.gz" "${IMAGE[@]}" \
          --id "demo-$PRESET" --wait | head -n 1)
echo "demo: scan $SCAN registered"

echo "demo: pulling the field and models as the visualisation station would"
# --scene: also scene.mrml, to open the result in 3D Slicer (File > Open):
# the preop atlas T1 under the field, the intraop T1, warped image and labels,
# coloured models.
bs pull --scan "$SCAN" --out "$OUT/result" \
   --parts field,field_h5,warped_image,warped_labels,models,metrics,timings \
   --scene --preop-image "$ATLAS_CACHE/t1.nii.gz" --intraop-image "$OUT/phantom/intraop_t1.nii.gz" >/dev/null
# The picture for the record: rendered by the daemon just after the result
# (off the latency path); pull waits for it if it is still being drawn.
bs pull --scan "$SCAN" --out "$OUT/result" --parts report >/dev/null
[[ -f $OUT/result/report.png ]] || { echo "demo: no report.png" >&2; exit 1; }
cp "$STORE/timing.jsonl" "$OUT/timing.jsonl"

echo
echo "Stage timings of $SCAN (seconds, from the daemon's timing log):"
grep "\"scan_id\":\"$SCAN\"" "$OUT/timing.jsonl" |
  sed -n 's/.*"seconds":\([0-9.e+-]*\).*"stage":"\([a-z_]*\)".*/\2 \1/p; t; s/.*"stage":"\([a-z_]*\)".*"seconds":\([0-9.e+-]*\).*/\1 \2/p' |
  awk '
    # The result is served from memory at scan.done and written (store) after
    # it; metrics, itk_field and report are made after it too (deferred parts).
    $1 == "store" || $1 == "metrics" || $1 == "itk_field" || $1 == "report" { late[++n] = sprintf("  %-10s %8.3f", $1, $2); next }
    { printf "  %-10s %8.3f\n", $1, $2; total += $2 }
    END {
      printf "  %-10s %8.3f   (to scan.done)\n", "sum", total
      if (n) print "  after scan.done (the write, then the deferred parts):"
      for (i = 1; i <= n; ++i) print late[i]
    }'
echo
echo "demo: outputs in $OUT/result:"
(cd "$OUT/result" && find . -type f | sort | sed 's|^\./|  |')
