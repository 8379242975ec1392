#!/usr/bin/env bash
# Issue "Safe by default", deliverable 4, second half: are short runs of the warm schedule cheap once inductor's
# on-disk cache holds the compiled layouts? verified:mpc, high speed, 256 held-out episodes x 10 s (78040-78295,
# named before use, 2026-11-28), one worker, one thread, --compile on: warm (shipped) and cold, each first with an
# empty inductor cache, then again with the cache that run filled.
set -eu
out=${1:-runs/short_runs}
mkdir -p "$out"
common="--driver verified:mpc --scenarios high_speed --seeds 78040-78295 --sim batched --lockstep 256 --workers 1 --threads 1 --compile on --duration 10"
for schedule in warm cold; do
  extra=""; [ "$schedule" = cold ] && extra="--set mpc.warm_iterations=0"
  cache="$out/inductor_$schedule"; rm -rf "$cache"
  for pass in empty_cache filled_cache; do
    rm -rf "$out/$schedule.$pass"
    TORCHINDUCTOR_CACHE_DIR="$cache" /usr/bin/time -f "$schedule $pass wall %e s" \
      mmpc evaluate $common $extra --out "$out/$schedule.$pass" > "$out/$schedule.$pass.log" 2>&1
    tail -1 "$out/$schedule.$pass.log"
  done
done
