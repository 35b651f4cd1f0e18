#!/usr/bin/env bash
# Builds the libFuzzer targets with clang (tests/fuzz/targets, a CMake project
# of its own) and runs each for a bounded time over its committed corpus.
# Fails on any crash, leak, sanitizer report or property violation; the input
# that triggered it is left in <build>/artifacts/<target>/.
#
#   run_fuzzers.sh [--seconds N] [--build DIR] [--jobs N] [--target message|nifti] [-- libFuzzer args]
#
# The CTest test fuzz_smoke runs it with --seconds 20. For a longer hunt:
#   tests/fuzz/run_fuzzers.sh --seconds 3600 --build build/tests/fuzz
# New inputs the fuzzers keep go to <build>/work/<target>/ (never into the
# repository); add a small regression seed to tests/fuzz/corpus/ by hand.
set -euo pipefail

here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
seconds=20
build="$here/../../build/tests/fuzz"
jobs=2
targets=(message nifti)
extra=()
while [[ $# -gt 0 ]]; do
  case "$1" in
    --seconds) seconds="$2"; shift 2 ;;
    --build) build="$2"; shift 2 ;;
    --jobs) jobs="$2"; shift 2 ;;
    --target) targets=("$2"); shift 2 ;;
    --) shift; extra=("$@"); break ;;
    *) echo "run_fuzzers.sh: unknown argument $1" >&2; exit 2 ;;
  esac
done

clangxx="${CLANGXX:-$(command -v clang++ || command -v clang++-14 || true)}"
clangc="${CLANGC:-$(command -v clang || command -v clang-14 || true)}"
if [[ -z "$clangxx" || -z "$clangc" ]]; then
  echo "FAIL: clang is not installed; the fuzz targets need clang and libclang-rt-14-dev (.ci/packages.txt)" >&2
  exit 1
fi

launcher=()
if command -v ccache > /dev/null; then launcher=(-DCMAKE_CXX_COMPILER_LAUNCHER=ccache -DCMAKE_C_COMPILER_LAUNCHER=ccache); fi
mkdir -p "$build"
cmake -S "$here/targets" -B "$build/build" \
  -DCMAKE_CXX_COMPILER="$clangxx" -DCMAKE_C_COMPILER="$clangc" "${launcher[@]}" > "$build/configure.log" ||
  { cat "$build/configure.log"; echo "FAIL: cannot configure the fuzz targets" >&2; exit 1; }
nice -n 5 cmake --build "$build/build" -j "$jobs" --target fuzz_message fuzz_nifti

status=0
for t in "${targets[@]}"; do
  work="$build/work/$t"
  artifacts="$build/artifacts/$t/"
  mkdir -p "$work" "$artifacts"
  # The nifti target bounds decompressed bytes at 32 MiB; the float image and
  # its re-encoding may take 4-5x that. Any single allocation above 256 MiB
  # (malloc_limit_mb) is a failure of the gzip-bomb bound.
  limits=(-rss_limit_mb=2048 -timeout=10)
  [[ "$t" == nifti ]] && limits+=(-malloc_limit_mb=256)
  echo "== fuzz_$t for ${seconds} s over tests/fuzz/corpus/$t"
  if "$build/build/fuzz_$t" -max_total_time="$seconds" "${limits[@]}" -dict="$here/$t.dict" \
       -artifact_prefix="$artifacts" -print_final_stats=1 "${extra[@]}" "$work" "$here/corpus/$t" \
       > "$build/fuzz_$t.log" 2>&1; then
    grep -E "^Done|stat::number_of_executed_units|stat::peak_rss_mb" "$build/fuzz_$t.log" || true
  else
    status=1
    tail -n 60 "$build/fuzz_$t.log"
    echo "FAIL: fuzz_$t found a problem; reproducer in $artifacts (full log $build/fuzz_$t.log)" >&2
  fi
done
exit $status
