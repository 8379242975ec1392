#!/usr/bin/env bash
# Deliverable 0 of the price of safety: verified:mpc in adversarial traffic at each frequency.
# Held-out seeds 75560-75815 (named before use, 2026-11-28); 1 and 2 Hz are refused (one line each).
set -u
out=${1:-runs/soundness}
for hz in 1 2; do
  mmpc evaluate --driver verified:mpc --scenarios high_speed_threats --sim batched --seeds 75560-75815 --lockstep 256 \
    --duration 10 --set frequency=$hz --out "$out/hz$hz" 2>&1 | tail -1
done
for hz in 5 10 15; do
  mmpc evaluate --driver verified:mpc --scenarios high_speed_threats --sim batched --seeds 75560-75815 --lockstep 128 \
    --workers 2 --threads 1 --duration 10 --set frequency=$hz --out "$out/hz$hz" > "$out/hz$hz.log" 2>&1
  grep -E "collisions|mean v" "$out/hz$hz.log" | head -4
done
