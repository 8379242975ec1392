"""Solver benchmark (same as `mmpc bench-solver`); see mmpc/bench_solver.py."""

import sys

from mmpc.cli import main

if __name__ == "__main__":
    sys.exit(main(["bench-solver", *sys.argv[1:]]))
