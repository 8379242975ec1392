#!/usr/bin/env bash
# Issue "Safe by default", deliverable 4: the shipped warm schedule against the cold one for verified:mpc,
# 1,024 held-out high-speed episodes x 40 s, paired per seed. Held-out seeds 75816-76839 (named before use, 2026-11-28).
set -eu
out=${1:-runs/warm_behind_check}
common="--driver verified:mpc --scenarios high_speed --seeds 75816-76839 --sim batched --lockstep 256 --workers 2 --threads 1 --compile on"
/usr/bin/time -f "warm wall %e s" mmpc evaluate $common --out "$out/warm" > "$out.warm.log" 2>&1
/usr/bin/time -f "cold wall %e s" mmpc evaluate $common --set mpc.warm_iterations=0 --out "$out/cold" > "$out.cold.log" 2>&1
python scripts/compare_drivers.py "cold=$out/cold" "warm=$out/warm" --metrics mean_speed,meta_cost_mean,failsafe_steps,fallback_steps,verified_share,task_return,solve_ms_per_episode_mean --allow-different-scenarios --out "$out"
