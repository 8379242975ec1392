"""How the solver runs its iterations: the ``compile="auto"`` decision and the kernel-compiler
probe, the compiled functions and their recompile limit, tiles and padding to a few compiled
layouts, and CUDA-graph capture and replay of a call layout's whole solve."""

from __future__ import annotations

import functools
import logging
import math
import os
from typing import Callable, NamedTuple, Optional

import torch

from mmpc.result import SolveResult, Trajectories, WarmStart
from mmpc.solver import iterations

logger = logging.getLogger(__name__)

#: Iterations per compiled graph in the ``compile=True`` path.
COMPILED_CHUNK = 10
#: Environment variable that decides ``compile="auto"`` (what :func:`mmpc.scenario.build_mpc`
#: passes): ``0`` eager, ``1`` compiled at once, unset: compiled in float32 where a kernel
#: compiler is found, each call layout once its eager solving would have cost
#: :data:`AUTO_COMPILE_AFTER_S`. Read in one place, :func:`auto_compile`; the command line's
#: ``--compile auto|on|off`` sets it (:func:`mmpc.cli.arguments.apply_compile`), so that worker
#: processes inherit the choice. Compiling is a run option, not part of a scenario.
COMPILE_ENV = "MMPC_COMPILE"
#: Widest SIMD register the compiled CPU kernels use (AVX-512) [bytes].
_SIMD_BYTES = 64
#: Recompiles of each compiled function a process allows (torch's default: 8): one per call layout
#: (the CPU kernels are shape-specialised); past it, new layouts solve eagerly.
RECOMPILE_LIMIT = 256

#: ``compile="auto"``: estimated seconds of eager solving of a call layout before it is compiled.
#: Compiling a layout takes 10-60 s, so a run that would not repay it (one ``mmpc drive`` episode:
#: ~12 s of solving) stays eager, and a long one pays at most this much more than compiling at once.
AUTO_COMPILE_AFTER_S = 20.0
#: Eager seconds per call (fixed, per (problem, goal) element of the whole schedule): CPU (one thread), CUDA; from
#: ``scripts/bench_solver.py`` (CPU: 13.6 ms at B = 1, 2.76 s at B = 4096; H100: ~60 ms to B = 4096).
EAGER_SECONDS = {False: (0.013, 0.67e-3), True: (0.06, 5e-6)}

#: Captured CUDA graphs an optimizer keeps (least recently used dropped first): each holds its own memory.
GRAPH_CACHE = 16

#: Elements per call of the compiled CPU path: a tile's (3N, 2, tile) samples and residuals
#: (~0.6 MB in float32) stay in a core's L2 cache between the products and the fused steps.
CPU_TILE_SIZE = 256


class Functions(NamedTuple):
    """The pure functions of one solve (:mod:`mmpc.solver.iterations`), eager or compiled."""

    layout: Callable
    resume: Callable
    summarise: Callable
    iterate: Callable


#: The eager functions: the reference, differentiable everywhere.
EAGER = Functions(iterations.layout, iterations.resume, iterations.summarise, iterations.iterate)


def compiled_functions(on_cpu: bool) -> Functions:
    """:data:`EAGER` through ``torch.compile``, specialised to each call layout's shapes.

    On CUDA: fused triton kernels (dynamic shapes, compiled at a small batch, ran 4-5x slower at
    large ones); each layout's whole solve is then captured as one CUDA graph (:class:`GraphSolve`):
    one launch per solve. On the CPU a C++ wrapper calls the kernels, without Python between them;
    the layout, the start and the outputs are compiled too (at small batch their eager
    op-by-op dispatch would cost as much as the iterations). Multiply-adds contract to fused
    multiply-adds (one rounding instead of two).
    """
    if on_cpu:
        options = {"cpp_wrapper": True, "cpp.enable_floating_point_contract_flag": "fast"}
        compile_function = functools.partial(torch.compile, fullgraph=True, dynamic=False, options=options)
    else:
        compile_function = functools.partial(torch.compile, fullgraph=True, dynamic=False)
    return Functions(*(compile_function(function) for function in EAGER))


def auto_compile(float32: bool, on_cpu: bool) -> tuple[bool, float]:
    """``compile="auto"`` -> (compiled, the default ``compile_after`` [s]): the compiled path where
    it is the fast one (float32, a kernel compiler found), each layout after
    :data:`AUTO_COMPILE_AFTER_S`, unless the environment variable ``MMPC_COMPILE`` says 0 (eager)
    or 1 (compiled at the first call)."""
    setting = compile_setting()
    if setting is not None:
        return setting, 0.0
    return float32 and kernel_compiler_found(on_cpu), AUTO_COMPILE_AFTER_S


def compile_setting() -> Optional[bool]:
    """The environment variable ``MMPC_COMPILE``: ``False`` (0, eager), ``True`` (1, compiled at the
    first call) or ``None`` (unset: each ``compile="auto"`` decides)."""
    setting = os.environ.get(COMPILE_ENV, "").strip()
    if setting not in ("", "0", "1"):
        raise ValueError(f"environment variable {COMPILE_ENV} must be 0, 1 or unset; got {setting!r}")
    return None if not setting else setting == "1"


def kernel_compiler_found(on_cpu: bool) -> bool:
    """Whether inductor finds what its kernels need: a C++ compiler on the CPU, triton on CUDA."""
    if not on_cpu:
        from torch.utils._triton import has_triton

        if not has_triton():
            logger.info("BatchOptimizer(compile='auto'): triton not found; eager on CUDA")
            return False
        return True
    from torch._inductor.cpp_builder import get_cpp_compiler

    try:
        get_cpp_compiler()
    except (RuntimeError, OSError) as error:
        logger.info("BatchOptimizer(compile='auto'): no C++ compiler (%s); eager", error)
        return False
    return True


def tiling(num_problems: int, num_goals: int, tile_size: Optional[int]) -> Optional[tuple[int, int]]:
    """(problems, goals) per tile for an E x G batch, or None when it fits one tile.

    Whole problems per tile when a problem's goals fit in one: a power of two of them, the one
    whose tile is nearest ``tile_size`` (within a factor of sqrt(2)), at most E rounded up to a
    power of two, so that batches of varying E (the warm and the cold rows of warm-started steps)
    share a few compiled layouts and a power-of-two E fills whole tiles; the problems left over
    take one smaller tile (:func:`problem_tiles`). Else one problem per tile with its goals split evenly.
    """
    if tile_size is None or num_problems * num_goals <= tile_size:
        return None
    if num_goals <= tile_size:
        nearest = 1 << max(0, round(math.log2(tile_size / num_goals)))
        return min(nearest, power_of_two_at_least(num_problems)), num_goals
    return 1, ceil_div(num_goals, ceil_div(num_goals, tile_size))


def problem_tiles(num_problems: int, tile_problems: int) -> list[tuple[int, int]]:
    """(first problem, problems) of each tile of E problems in tiles of ``tile_problems``: whole
    tiles, then the rest in one tile of the next power of two (padded with copies of the last
    problem: less than half of it, where whole tiles would pad up to a tile)."""
    whole = num_problems - num_problems % tile_problems
    tiles = [(first, tile_problems) for first in range(0, whole, tile_problems)]
    if whole < num_problems:
        tiles.append((whole, min(power_of_two_at_least(num_problems - whole), tile_problems)))
    return tiles


def power_of_two_at_least(count: int) -> int:
    return 1 << (count - 1).bit_length()


def problem_bucket(num_problems: int, num_goals: int, tile_size: Optional[int]) -> int:
    """Problems to solve for an E x G batch that fits one tile: E rounded up to a power of two
    (at most a full tile), so that batches of varying E (rows that replan, episodes that end)
    share a few compiled layouts instead of compiling one each. Without tiles: E."""
    if tile_size is None:
        return num_problems
    return max(num_problems, min(power_of_two_at_least(num_problems), tile_size // num_goals))


def graph_bucket(num_problems: int) -> int:
    """Problems to solve on the compiled CUDA path: E rounded up to 1-8, 10, 12, 14, 16, 20, 24, 28,
    32, 40, ... (four sizes per octave, at most 25 % padding), so that batches of varying E share
    a few captured graphs."""
    if num_problems <= 8:
        return num_problems
    step = 1 << (num_problems.bit_length() - 3)
    return ceil_div(num_problems, step) * step


class GraphSolve:
    """One call layout's solve captured as a CUDA graph: static inputs copied in, replayed, the
    outputs cloned out."""

    def __init__(self, graph: "torch.cuda.CUDAGraph", inputs: tuple[Optional[torch.Tensor], ...], output: SolveResult) -> None:
        self.graph, self.inputs, self.output = graph, inputs, output

    @staticmethod
    def capture(solve, inputs: tuple[Optional[torch.Tensor], ...]) -> Optional["GraphSolve"]:
        """Warm ``solve`` up on ``inputs`` (compiling it) on a side stream, then capture it; ``None``
        (warned) when the capture fails, so that the caller runs ``solve`` without a graph."""
        static = tuple(None if t is None else t.clone() for t in inputs)
        device = next(t.device for t in inputs if t is not None)
        side = torch.cuda.Stream(device)
        side.wait_stream(torch.cuda.current_stream(device))
        try:
            with torch.cuda.stream(side):
                solve(*static)  # compiles; allocates the cuBLAS workspace outside the capture
            torch.cuda.current_stream(device).wait_stream(side)
            graph = torch.cuda.CUDAGraph()
            with torch.cuda.graph(graph):
                output = solve(*static)
        except RuntimeError as error:
            torch.cuda.synchronize(device)
            logger.warning("BatchOptimizer: capturing a CUDA graph failed (%s); this layout runs compiled without a graph",
                           error)
            return None
        return GraphSolve(graph, static, output)

    def replay(self, inputs: tuple[Optional[torch.Tensor], ...]) -> SolveResult:
        for static, given in zip(self.inputs, inputs):
            if static is not None:
                static.copy_(given)
        self.graph.replay()
        return _clone_result(self.output)


def _clone_result(result: SolveResult) -> SolveResult:
    """A copy of every per-element tensor of ``result`` (the sample times are a shared buffer)."""
    trajectories = Trajectories(result.trajectories.times, *(field.clone() for field in result.trajectories[1:]))
    warm = None if result.warm is None else WarmStart(*(field.clone() for field in result.warm))
    return result._replace(trajectories=trajectories, warm=warm, **{
        name: None if getattr(result, name) is None else getattr(result, name).clone()
        for name in SolveResult._fields if name not in ("trajectories", "warm")
    })


def ceil_div(numerator: int, denominator: int) -> int:
    return -(-numerator // denominator)


def repeat_last(tensor: Optional[torch.Tensor], dim: int, size: int) -> Optional[torch.Tensor]:
    """``tensor`` grown along ``dim`` to ``size`` entries with copies of its last one (``None`` stays ``None``)."""
    if tensor is None:
        return None
    index = torch.arange(size, device=tensor.device).clamp_max(tensor.shape[dim] - 1)
    return tensor.index_select(dim, index)


def repeat_warm(warm: Optional[WarmStart], dim: int, size: int) -> Optional[WarmStart]:
    """:func:`repeat_last` of every field of a warm start (``None`` stays ``None``)."""
    return None if warm is None else WarmStart(*(repeat_last(field, dim, size) for field in warm))


def goal_padding(num_problems: int, num_goals: int, element_size: int) -> int:
    """Goals to append so that a row of E G' elements fills whole SIMD vectors (compiled CPU path).

    The batch is the innermost, contiguous dimension of every fused kernel; a row that ends in
    a partial vector takes masked loads and stores. Padding is used only where it adds less
    than one vector per row (always for E = 1), so it never adds work to a large batch.
    """
    width = _SIMD_BYTES // element_size
    for padded in range(num_goals, num_goals + width + 1):
        if num_problems * padded % width == 0:
            return padded - num_goals if num_problems * (padded - num_goals) < width else 0
    return 0
