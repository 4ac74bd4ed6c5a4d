#!/bin/bash
# tune-loops' tuner-vs-search verdict over base seeds (the evaluation's fresh seeds, EVAL_SEED, are the same for all):
#   bash benchmarks/tune_loops_seeds.sh OUT [LOOPS [SEEDS]]     e.g. bash benchmarks/tune_loops_seeds.sh /tmp/tls "drhe-safe drhe" "1 2 3"
# One `jaxnc run tune-loops --set loops=L seed=S` per (loop, seed) into OUT/L-S (a finished one is skipped); prints
# each run's paired tuned - search difference and verdict.
set -e
OUT=${1:?OUT folder}; LOOPS=${2:-"drhe-safe drhe"}; SEEDS=${3:-"1 2 3 4 5 6 7 8 9"}
ROOT=$(cd "$(dirname "$0")/.." && pwd); JAXNC=${JAXNC:-$ROOT/.venv/bin/jaxnc}
mkdir -p "$OUT"
for L in $LOOPS; do
  for S in $SEEDS; do
    O=$OUT/$L-$S
    [ -f "$O/tables.md" ] || "$JAXNC" run tune-loops --seeds 512 --set loops=$L seed=$S --out "$O" --no-progress > "$O.log" 2>&1
    echo "$L seed $S $(grep "^| $L " "$O/tables.md" | tail -1 | awk -F'|' '{print $(NF-2), "|", $(NF-1)}')"
  done
done
