"""Evaluation benchmark (same as `mmpc bench-evaluate`); see mmpc/bench_evaluate.py."""

import sys

from mmpc.cli import main

if __name__ == "__main__":
    sys.exit(main(["bench-evaluate", *sys.argv[1:]]))
