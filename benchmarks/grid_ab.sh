#!/bin/bash
# Usage: git archive b126f55 | tar -x -C /tmp/grid_old; git archive HEAD | tar -x -C /tmp/grid_new (each with jaxnc/experiments -> ../experiments); then run this script.
# A = b126f55 (2026-11-24, grid 13:55), B = 7d76239 (main, grid 20:03). Subset of the grid; CPU time per run.
S="-s case=all N=1,10 path=lissajous"
run() { # tree cache label
  rm -rf /tmp/gab_out_$3
  /usr/bin/time -f "$3 wall %e user %U sys %S" env PYTHONPATH=/tmp/grid_$1 JAXNC_CACHE_DIR=$2 /work/main/.venv/bin/python -m jaxnc.cli run mecanum-grid $S --cpu-devices 2 --out /tmp/gab_out_$3 --cache-dir $2 --no-progress > /tmp/gab_$3.log 2>&1
  tail -1 /tmp/gab_$3.log; uptime
}
rm -rf /tmp/gab_cA /tmp/gab_cB; mkdir -p /tmp/gab_cA /tmp/gab_cB
run old /tmp/gab_cA coldA
run new /tmp/gab_cB coldB
run old /tmp/gab_cA warmA1
run new /tmp/gab_cB warmB1
run new /tmp/gab_cB warmB2
run old /tmp/gab_cA warmA2
