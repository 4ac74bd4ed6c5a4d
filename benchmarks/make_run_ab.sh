#!/bin/bash
# `make run`'s command, cold (empty compilation cache) and warm (the cold run's cache), trees A and B
# in turn, ROUNDS times (A B A B cold, then A B warm, each round). Each run is its own process
# session at autogroup nice -20 (needs root), so that other jobs on the machine take little of its
# cores; the instrumentation is benchmarks/profile_cli.py of the tree run.
#   usage: benchmarks/make_run_ab.sh TREE_A TREE_B OUT_DIR [ROUNDS]     (a tree: a checkout or `git archive`)
set -u
A=$1; B=$2; D=$3; R=${4:-3}; mkdir -p "$D"
PY=${PYTHON:-.venv/bin/python}; PY=$(realpath "$PY")
one() {   # tree tag cache out
  rm -rf "$4"
  setsid bash -c "echo -20 > /proc/self/autogroup 2>/dev/null; cd '$1'; exec nice -n -20 /usr/bin/time \
    -f 'TIME %e wall %U user %S sys' env PYTHONPATH='$1' '$PY' benchmarks/profile_cli.py --top 3 -- run mecanum \
    --seeds 256 --set case=all --out '$4' --cache-dir '$3' --no-progress" > "$D/$2.txt" 2>&1
  echo "$2 $(date -u +%T) load=$(cut -d' ' -f1 /proc/loadavg) $(grep '^TIME' "$D/$2.txt") |" \
       "$(grep -o 'persistent cache: .*' "$D/$2.txt") | $(grep -o 'compilations over 0.5 s.*' "$D/$2.txt")"
}
for i in $(seq 1 "$R"); do
  for t in A B; do
    T=$A; [ $t = B ] && T=$B
    rm -rf "$D/cache_$t$i"; mkdir -p "$D/cache_$t$i"
    one "$T" "cold_$t$i" "$D/cache_$t$i" "$D/out_cold_$t$i"
  done
  for t in A B; do
    T=$A; [ $t = B ] && T=$B
    one "$T" "warm_$t$i" "$D/cache_$t$i" "$D/out_warm_$t$i"
  done
done
