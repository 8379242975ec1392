#!/bin/bash
# Issue 65 held-out checks, the rest (cruise naturalistic without cut-ins cut to 512 episodes to fit the session).
cd /work/main
while pgrep -f "runs/final/hs_thr_on" > /dev/null; do sleep 15; done
run() { name=$1; shift; echo "== $name $(date +%T) $(git rev-parse --short HEAD)"; mmpc evaluate --driver verified:mpc --sim batched --lockstep 256 --out runs/final/$name "$@" > runs/final/$name.log 2>&1; echo "   done $(date +%T) rc=$?"; grep -E "^episodes|^collisions|ego's fault|mean v|meta cost|v-v_c" runs/final/$name.log; }
run cr_thr_on  --scenarios cruise_threats --seeds 92256-94303 --duration 10 --set traffic.ego_as_follower=true
run cr_nat_off --scenarios cruise --seeds 95328-95839 --duration 40
