#!/bin/bash
# Issue 66's smoke: a 2x10^4-step `mmpc rl train` of every shipped recipe in each world, behind the
# default (verified) layer, one thread. The high-speed recipe on the batched world ran in session 39.
set -u
out=runs/recipe_smokes
mkdir -p $out
for world in batched highway-env; do
  for recipe in cruise_task high_speed_task smoke high_speed; do
    [ "$world/$recipe" = "batched/high_speed" ] && continue
    run=$out/${recipe}_${world}
    [ -f $run/model.zip ] && continue
    echo "$(date -u +%T) start $run"
    start=$(date +%s)
    OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 mmpc rl train --algo ppo --config $recipe --sim $world \
      --timesteps 20000 --no-eval --seed 0 --out $run > $run.log 2>&1
    echo "$(date -u +%T) done $run rc=$? in $(( $(date +%s) - start )) s"
  done
done
