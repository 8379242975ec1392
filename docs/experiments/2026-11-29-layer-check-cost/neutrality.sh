#!/bin/bash
# Warm frame solves in the default RL scenario (rl_highway_fast): the always-defer agent and the
# random agent behind the default (verified, frame-replanning) layer, cold against warm, tuning seeds.
set -u
out=runs/warm_frames
for warm in 0 10; do
  mmpc evaluate --driver safe-expert,safe-random --scenarios rl_highway_fast --sim batched \
    --seeds 71600-71631 --duration 30 --lockstep 32 --threads 1 --compile on \
    --set mpc.warm_iterations=$warm --out $out/warm$warm > $out/warm$warm.log 2>&1
done
