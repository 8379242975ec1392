#!/usr/bin/env bash
# Issue "Safe by default", deliverable 4: a short compiled run of the warm schedule (shipped) against the cold one
# (--set mpc.warm_iterations=0), each from an empty inductor cache: verified:mpc, high speed, 64 x 10 s, tuning seeds
# 71500-71563, one worker, one thread, --compile on.
set -eu
out=${1:-runs/one_layout_short}; mkdir -p "$out"
common="--driver verified:mpc --scenarios high_speed --seeds 71500-71563 --sim batched --lockstep 64 --workers 1 --threads 1 --compile on --duration 10"
for schedule in warm cold; do
  extra=""; [ "$schedule" = cold ] && extra="--set mpc.warm_iterations=0"
  rm -rf "$out/inductor_$schedule" "$out/$schedule"
  TORCHINDUCTOR_CACHE_DIR="$out/inductor_$schedule" /usr/bin/time -f "$schedule wall %e s" \
    mmpc evaluate $common $extra --out "$out/$schedule" > "$out/$schedule.log" 2>&1
  tail -1 "$out/$schedule.log"
  grep -E "mean v|meta cost|solve ms / episode|collisions" "$out/$schedule.log" | head -4
done
