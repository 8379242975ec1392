"""Run `mmpc ARGS` and print, at exit, the compiled graphs per solver function and the process time."""
import sys, atexit, time
from torch._dynamo.eval_frame import _debug_get_cache_entry_list
from mmpc.solver import execution
start = time.perf_counter()
@atexit.register
def report():
    counts = {f.__name__: len(_debug_get_cache_entry_list(f.__code__)) for f in execution.EAGER}
    print("GRAPHS", sum(counts.values()), counts, "wall %.0f s" % (time.perf_counter() - start))
from mmpc.cli.main import main
sys.argv = ["mmpc", *sys.argv[1:]]
main()
