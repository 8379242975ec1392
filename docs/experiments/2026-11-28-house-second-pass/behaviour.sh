#!/usr/bin/env bash
# behaviour.sh OUT: the episodes the house's second pass keeps identical (eager, both worlds, seeds 0-7, 10 s).
# Run it before and after a change (each tree installed, or on PYTHONPATH), then: python same.py BEFORE AFTER
set -e
OUT=$1; export MMPC_COMPILE=0
mkdir -p "$OUT"
run() { name=$1; shift; python -m mmpc.cli evaluate "$@" --seeds 0-7 --duration 10 --workers 2 --out "$OUT/$name" > "$OUT/$name.log" 2>&1; }
run he --driver mpc,frenet --scenarios cruise,high_speed
run batched --driver mpc,frenet --scenarios cruise,high_speed --sim batched
run rl_cruise --driver sb3:cruise_task_ppo,proposer:cruise --scenarios cruise
run rl_hs --driver sb3:high_speed_ppo,proposer:high_speed --scenarios high_speed
run rl_cruise_b --driver sb3:cruise_task_ppo --scenarios cruise --sim batched
