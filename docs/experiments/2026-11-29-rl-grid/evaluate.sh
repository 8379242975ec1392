#!/usr/bin/env bash
# The grid's held-out evaluations and their tables (issue 67): every trained agent of a recipe beside
# always-defer, the verified expert, the unprotected expert and the plain agents, on seeds no run
# was tuned on; one `mmpc evaluate` per (scenario, world), resumed where it stopped.
#   bash docs/experiments/2026-11-29-rl-grid/evaluate.sh cruise batched [WORKERS]
#   bash docs/experiments/2026-11-29-rl-grid/evaluate.sh cruise highway-env [WORKERS]
# Seeds: cruise 96480-97479 (batched) / 63296-63495 (highway-env); high_speed 97480-98479 / 63496-63695.
set -eu
scenario=$1 world=$2 workers=${3:-2}
cd "$(dirname "$0")/../../.."
recipe=${scenario}_task
[ "$scenario" = cruise ] || [ "$scenario" = high_speed ] || { echo "scenario: cruise or high_speed, got $scenario" >&2; exit 2; }
case "$scenario/$world" in
  cruise/batched) seeds=96480-97479 lockstep=480 ;;
  cruise/highway-env) seeds=63296-63495 lockstep=50 ;;
  high_speed/batched) seeds=97480-98479 lockstep=480 ;;
  high_speed/highway-env) seeds=63496-63695 lockstep=50 ;;
  *) echo "world: batched or highway-env, got $world" >&2; exit 2 ;;
esac
agents() {  # kind algo: the finished runs' drivers, '|'-joined (plain agents: cruise_task's, see queue.sh)
  local kind=$1 algo=$2 prefix folder list=()
  prefix=$([ "$kind" = safe ] && echo "" || echo "plain_")
  folder=$([ "$kind" = safe ] && echo "$recipe" || echo cruise_task)
  for seed in 0 1 2; do
    model=runs/grid/$folder/${prefix}${algo}_${seed}/model.zip
    [ -f "$model" ] && list+=("sb3:$model")
  done
  (IFS='|'; echo "${list[*]:-}")
}
rows=() drivers=()
for kind in safe plain; do
  for algo in ppo dqn; do
    group=$(agents $kind $algo)
    [ -n "$group" ] || continue
    label="$(echo $algo | tr a-z A-Z) $([ $kind = safe ] && echo "behind the layer" || echo "plain (no layer)")"
    rows+=(--row "$label=$group")
    drivers+=(${group//|/ })
  done
done
baselines="safe-expert:$recipe verified:mpc mpc"
out=runs/grid/eval/${scenario}_${world}
mmpc evaluate --driver "$(echo $baselines ${drivers[*]} | tr ' ' ',')" --scenarios "$scenario" --seeds "$seeds" \
  --sim "$world" --lockstep "$lockstep" --workers "$workers" --out "$out"
python docs/experiments/2026-11-29-rl-grid/table.py "$out" --reference "always defer=safe-expert:$recipe" "${rows[@]}" \
  --row "verified expert=verified:mpc" --row "unprotected expert=mpc" --out "$out"
