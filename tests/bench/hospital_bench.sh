#!/bin/sh
# The hospital-variation suite, one subject (one preop warm-up and its cases)
# at a time under a time limit: a warm-up that never finishes (the mesher's
# unbounded sliver exudation, issue 17) is recorded as "did not finish", not
# waited for. Prints the suite's JSON document on stdout.
#   BUILD=build LIMIT=900 tests/bench/hospital_bench.sh [--modes labels+image,labels,image] [--cases a,b]
# Records of every run are kept in $RECORDS (default hospital_records.ndjson).
set -u
BUILD=${BUILD:-build}
LIMIT=${LIMIT:-900}
RECORDS=${RECORDS:-hospital_records.ndjson}
BENCH="$BUILD/tests/bench/brainshift_hospital_bench"
CACHE=${ATLAS_CACHE:-$BUILD/brainshift-atlas}
: > "$RECORDS"
SUBJECTS=$("$BENCH" --list-subjects "$@")
# Each run below is given one subject: a --subjects of the caller's would
# otherwise run every listed subject in every pass of the loop.
ARGS=""
skip=0
for a in "$@"; do
  if [ "$skip" -eq 1 ]; then skip=0; continue; fi
  case "$a" in
    --subjects) skip=1 ;;
    --subjects=*) ;;
    *) ARGS="$ARGS $a" ;;
  esac
done
for subject in $SUBJECTS; do
  echo "subject $subject (limit $LIMIT s)" >&2
  # shellcheck disable=SC2086  # ARGS: the caller's words, none with spaces
  timeout "$LIMIT" "$BENCH" --atlas-cache "$CACHE" --subjects "$subject" $ARGS >> "$RECORDS"
  rc=$?
  if [ "$rc" -eq 124 ]; then
    printf '{"record":"preop","subject":"%s","note":"stopped by the time limit of %s s"}\n' "$subject" "$LIMIT" >> "$RECORDS"
  elif [ "$rc" -ne 0 ]; then
    printf '{"record":"preop","subject":"%s","note":"the benchmark exited with status %s"}\n' "$subject" "$rc" >> "$RECORDS"
  fi
done
"$BENCH" --summarise "$RECORDS" "$@"
