#!/usr/bin/env bash
# Issue "Safe by default", deliverable 4: the compiled graphs a short verified:mpc run compiles, warm schedule
# (shipped) against cold (--set mpc.warm_iterations=0), each with an empty inductor cache. Tuning seeds 71400-71463.
set -eu
here=$(dirname "$0"); out=${1:-runs/one_layout}; mkdir -p "$out"
common="evaluate --driver verified:mpc --scenarios high_speed --sim batched --seeds 71400-71463 --duration 3 --lockstep 64 --workers 1 --threads 1 --compile on"
for schedule in warm cold; do
  extra=""; [ "$schedule" = cold ] && extra="--set mpc.warm_iterations=0"
  rm -rf "$out/inductor_$schedule" "$out/$schedule"
  TORCHINDUCTOR_CACHE_DIR="$out/inductor_$schedule" python "$here/graph_count.py" $common $extra --out "$out/$schedule" > "$out/$schedule.log" 2>&1
  echo "$schedule: $(grep GRAPHS "$out/$schedule.log")"
done
