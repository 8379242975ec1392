#!/usr/bin/env bash
# The RL grid of issue 67, one run at a time per worker; start one worker per core:
#   bash docs/experiments/2026-11-29-rl-grid/queue.sh plain safe   # worker 1: plain runs first, then safe
#   bash docs/experiments/2026-11-29-rl-grid/queue.sh safe         # worker 2: safe runs
# A finished run is skipped, a stopped one resumes from its latest checkpoint, one another worker
# holds (its lock) is left to it. Runs land in runs/grid/<recipe>/<kind>_<algo>_<seed>.
# The plain runs train under cruise_task only: without the layer the two recipes are one experiment
# (the same world, traffic, car, observation, reward and meta-speeds; only the layer's expert differs),
# so evaluate.sh gives both scenarios the cruise_task plain agents.
set -u
STEPS=${STEPS:-500000}
export OMP_NUM_THREADS=1 MKL_NUM_THREADS=1
cd "$(dirname "$0")/../../.."
finished() {  # the run trained its budget
  python - "$1" "$STEPS" <<'PY'
import sys, yaml, pathlib
path = pathlib.Path(sys.argv[1]) / "config.yaml"
try:
    record = yaml.safe_load(path.read_text())
except OSError:
    sys.exit(1)
sys.exit(0 if (pathlib.Path(sys.argv[1]) / "model.zip").is_file() and record.get("trained_timesteps", 0) >= int(sys.argv[2]) else 1)
PY
}
run() {  # kind algo recipe seed
  local kind=$1 algo=$2 recipe=$3 seed=$4
  local name=$([ "$kind" = safe ] && echo "${algo}_${seed}" || echo "plain_${algo}_${seed}")
  local out=runs/grid/$recipe/$name
  finished "$out" && return 0
  [ -e "$out/.train.lock" ] && ! flock -n "$out/.train.lock" true && return 0  # another worker holds it
  if ls "$out"/checkpoints/*_steps.zip >/dev/null 2>&1; then
    echo "$(date +%T) resume $out"; mmpc rl train --resume --out "$out" --timesteps "$STEPS" --no-eval >> "runs/grid/$recipe/$name.log" 2>&1
  else
    rm -rf "$out"; mkdir -p "runs/grid/$recipe"
    echo "$(date +%T) start $out"
    mmpc rl train --algo "$algo" --config "$recipe" --env "$kind" --sim batched --timesteps "$STEPS" --seed "$seed" \
      --no-eval --out "$out" >> "runs/grid/$recipe/$name.log" 2>&1
  fi
  echo "$(date +%T) end $out (rc $?)"
}
for kind in "$@"; do
  for recipe in cruise_task high_speed_task; do
    [ "$kind" = plain ] && [ "$recipe" != cruise_task ] && continue
    for algo in ppo dqn; do
      for seed in 0 1 2; do run "$kind" "$algo" "$recipe" "$seed"; done
    done
  done
done
