"""Safe-layer VecEnv benchmark: agent steps per second of E vectorized safe environments with one
batched solve per frame vs one solve per environment (see mmpc/rl/bench.py).

    python scripts/bench_safe_vecenv.py --envs 64 --steps 3 --out benchmarks/bench_safe_vecenv.json
"""

import argparse
import sys
from pathlib import Path

from mmpc.rl.bench import format_report, run_benchmark
from mmpc.rl.config import load_rl_config


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", default="safe_highway", help="RL config name in configs/rl or a YAML path")
    parser.add_argument("--envs", type=int, default=64, help="vectorized environments E (default 64)")
    parser.add_argument("--steps", type=int, default=3, help="timed vectorized steps per variant (default 3)")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="benchmarks/bench_safe_vecenv.json", help="JSON report")
    args = parser.parse_args(argv)
    report = run_benchmark(load_rl_config(args.config), num_envs=args.envs, steps=args.steps, seed=args.seed,
                           threads=args.threads, out=Path(args.out))
    print(format_report(report))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
