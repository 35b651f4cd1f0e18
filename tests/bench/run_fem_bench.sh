#!/usr/bin/env bash
# Runs the Figure-6 FEM benchmark matrix on the Colin27 brain and prints one
# JSON object per line: np 1 and 2 x each solver at the published mesh size,
# then a sweep of mesh sizes with the warm direct solver.
#   tests/bench/run_fem_bench.sh BUILD_DIR [ATLAS_CACHE] > fem_bench.jsonl
set -euo pipefail
BUILD=${1:?build dir}
CACHE=${2:-$BUILD/brainshift-atlas}
BENCH=$BUILD/tests/bench/brainshift_fem_bench
export OMPI_ALLOW_RUN_AS_ROOT=1 OMPI_ALLOW_RUN_AS_ROOT_CONFIRM=1 OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1
run() { local np=$1; shift; mpirun --allow-run-as-root --oversubscribe -np "$np" "$BENCH" --atlas-cache "$CACHE" "$@"; }
for np in 1 2; do
  run "$np" --solver direct --package cholmod
  run "$np" --solver direct --package mumps
  run "$np" --solver cg_gamg
  run "$np" --solver gmres_bjacobi
done
run 1 --solver direct --dirichlet row_replacement --package mumps
# Mesh-size sweep (cell / facet / distance mm): ~10k, ~43k, ~150k, ~400k nodes.
run 1 --solver direct --cell-size 6.5 --facet-size 3.6 --facet-distance 2.0 --repeat 3
run 1 --solver direct --cell-size 2.2 --facet-size 1.35 --facet-distance 1.0 --repeat 3
# At ~400k nodes CHOLMOD's 32-bit factor overflows ("problem too large"):
# the iterative solvers carry the sweep there.
run 1 --solver cg_gamg --cell-size 2.2 --facet-size 1.35 --facet-distance 1.0 --repeat 3
run 1 --solver cg_gamg --cell-size 1.55 --facet-size 0.95 --facet-distance 0.7 --repeat 3
run 2 --solver gmres_bjacobi --cell-size 1.55 --facet-size 0.95 --facet-distance 0.7 --repeat 3
