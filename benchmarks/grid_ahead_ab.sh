#!/bin/bash
# A = a tree of the previous commit (git archive HEAD~ | tar -x -C /tmp/s53/A; ln -s ../experiments A/jaxnc/experiments), B = this tree
# A B B A of a one-path grid, each run with an empty cache; $1 = path setting
P=${1:-lissajous}
for T in A B B A; do
  if [ $T = A ]; then R=/tmp/s53/A; else R=/work/main; fi
  O=$(mktemp -d); C=$(mktemp -d)
  s=$(date +%s.%N)
  ( cd $R && PYTHONPATH=$R /usr/bin/time -f "%U user %S sys %e wall" /work/main/.venv/bin/python -c 'import sys; from jaxnc.cli import main; sys.exit(main())' run mecanum-grid -s path=$P --cpu-devices 2 --out $O --cache-dir $C --no-progress 2>&1 | tail -2 )
  echo "$T $(date -u +%H:%M) load $(cut -d' ' -f1 /proc/loadavg)"
  cp $O/tables_$P.csv /tmp/s53/tables_$T.csv
done
