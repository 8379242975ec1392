"""Count the call layouts a run would compile (eager run, layouts recorded)."""
import sys, collections, atexit
from mmpc.solver.optimizer import BatchOptimizer
seen = collections.Counter()
def deferred(self, layout, elements):
    seen[layout] += 1
    return True
BatchOptimizer._deferred = deferred
@atexit.register
def report():
    print("LAYOUTS", len(seen))
    for k, v in sorted(seen.items(), key=lambda kv: -kv[1]): print("  ", k, v)
from mmpc.cli.main import main
sys.argv = ["mmpc", *sys.argv[1:]]
main()
