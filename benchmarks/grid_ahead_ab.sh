#!/bin/bash
# A B B A of a one-path mecanum-grid, each run with an empty compilation cache, two CPU devices.
#   bash benchmarks/grid_ahead_ab.sh [PATH [REV]]     (PATH: lissajous, lane_change or turn180; REV: the A tree, default HEAD~)
# A = a checkout of REV (git archive), B = this working tree (or the tree B=DIR); prints each run's cell-loop time, user
# CPU and wall, and whether the four runs' tables are byte for byte the same. WARM=1: every run uses one compilation
# cache, filled first by a run of B that is not counted (what is left is tracing, loading and the cells).
set -e
P=${1:-lissajous}; REV=${2:-HEAD~}
ROOT=$(cd "$(dirname "$0")/.." && pwd); PY=${PY:-$ROOT/.venv/bin/python}
A=$(mktemp -d); (cd "$ROOT" && git archive "$REV") | tar -x -C "$A"; ln -s ../experiments "$A/jaxnc/experiments"
T=$(mktemp -d); BT=${B:-$ROOT}; W=$(mktemp -d)
if [ -n "$WARM" ]; then
  ( cd "$BT" && PYTHONPATH="$BT" "$PY" -c 'import sys; from jaxnc.cli import main; sys.exit(main())' \
      run mecanum-grid -s path="$P" --cpu-devices 2 --out "$(mktemp -d)" --cache-dir "$W" --no-progress >/dev/null 2>&1 )
fi
for X in A B B A; do
  if [ $X = A ]; then R=$A; else R=$BT; fi
  O=$(mktemp -d); if [ -n "$WARM" ]; then C=$W; else C=$(mktemp -d); fi
  ( cd "$R" && PYTHONPATH="$R" /usr/bin/time -f "%U user %S sys %e wall" "$PY" -c 'import sys; from jaxnc.cli import main; sys.exit(main())' \
      run mecanum-grid -s path="$P" --cpu-devices 2 --out "$O" --cache-dir "$C" --no-progress 2>&1 | tail -2 )
  echo "$X $(date -u +%H:%M) load $(cut -d' ' -f1 /proc/loadavg)"
  cp "$O/tables_$P.csv" "$T/tables_$X.csv"
done
cmp "$T/tables_A.csv" "$T/tables_B.csv" && echo "tables identical"
