#!/bin/bash
# Held-out checks of issue 65 at the final check (f64c0da), seeds named before use.
cd /work/main
run() { name=$1; shift; echo "== $name $(date +%T)"; mmpc evaluate --driver verified:mpc --sim batched --lockstep 256 --out runs/final/$name "$@" > runs/final/$name.log 2>&1; echo "   done $(date +%T) rc=$?"; grep -E "^episodes|^collisions|ego's fault|mean v|meta cost|v-v_c" runs/final/$name.log; }
run hs_nat_on  --scenarios high_speed --seeds 88160-89183 --duration 40 --set traffic.ego_as_follower=true
run cr_nat_on  --scenarios cruise --seeds 89184-90207 --duration 40 --set traffic.ego_as_follower=true
run hs_thr_on  --scenarios high_speed_threats --seeds 90208-92255 --duration 10 --set traffic.ego_as_follower=true
run cr_thr_on  --scenarios cruise_threats --seeds 92256-94303 --duration 10 --set traffic.ego_as_follower=true
run hs_nat_off --scenarios high_speed --seeds 94304-95327 --duration 40
run cr_nat_off --scenarios cruise --seeds 95328-96351 --duration 40
