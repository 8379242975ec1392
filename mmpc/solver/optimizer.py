"""The batch optimizer, :class:`BatchOptimizer`: an ``nn.Module`` holding the cached operators that
runs the alternating-minimisation schedule (:mod:`mmpc.solver.iterations`) on checked inputs
(:mod:`mmpc.solver.checks`), with early exits and warm starts, eager or compiled
(:mod:`mmpc.solver.execution`)."""

from __future__ import annotations

import functools
import logging
import math
import time
from collections import OrderedDict
from typing import Optional

import torch
from torch import nn

from mmpc.compaction import compact
from mmpc.solver.basis import bernstein_basis, bernstein_shift
from mmpc.solver.operators import build_operators
from mmpc.problem import ProblemBatch
from mmpc.result import SolveResult, Trajectories, WarmStart
from mmpc.solver import checks, execution, iterations
from mmpc.solver.config import OptimizerConfig

logger = logging.getLogger(__name__)


class BatchOptimizer(nn.Module):
    """Batch non-holonomic trajectory optimizer with every constant matrix cached as a buffer.

    Solves, for each of E problems and each of its G goals, ::

        min  sum_t xddot^2 + yddot^2 + psiddot^2   (weighted)  [+ lane keeping on y, config.lane_weight]
        s.t. xdot = v cos psi, ydot = v sin psi, v_min <= v <= v_max, |(xddot, yddot)| <= a_max,
             outside every obstacle ellipse (a, b) at every sample, boundary conditions,

    in ``config.iterations`` alternating-minimisation iterations from a cold start (with
    ``config.exit_checks``, an element feasible at a check stops there). The
    projections may aim a margin inside the feasible set (larger ellipses, a smaller
    acceleration disc: ``config.obstacle_backoff``, ``acceleration_backoff``); the checks and the
    status use the constraints themselves, with their tolerances. Internally the batch is the
    last (column) dimension so that every step is a constant matrix times a wide right-hand
    side; inputs and outputs keep the batch first.

    Args:
        config: optimizer settings; defaults are the paper authors' values.
        dtype: floating dtype of the buffers and of every computation (inputs are cast once).
            Build with ``dtype=torch.float64`` rather than ``.to(torch.float64)`` later, which
            would keep the float32-rounded matrices.
        device: where the buffers live; inputs must already be there.
        compile: True to run the iterations through ``torch.compile`` (fused elementwise kernels, one
            call per chunk of iterations). The first solve of every new batch shape compiles
            (seconds on a CPU); later solves are several times faster than eager. On
            the CPU the start (cold or warm: one function) and the outputs are compiled too, C++ wrappers call the
            kernels, and a small batch is padded with copies of its last goal to whole SIMD
            vectors (the copies are dropped from the result). On CUDA every call layout's whole
            solve is captured once as a CUDA graph and replayed (E rounded up to a few sizes per
            octave, :func:`mmpc.solver.execution.graph_bucket`); results are copied out of the graph. Eager (the
            default) is the reference and supports autograd
            everywhere: a compiled optimizer solves inputs that require grad (autograd enabled)
            eagerly, with torch's sin, cos and atan2 (the same values to float32 rounding), as
            its compiled graphs are not differentiated. On the CPU every call layout gets its
            own shape-specialised kernels (a few seconds to compile each, 10-30 s on CUDA; torch's
            dynamic-shape kernels, its default from a second shape on, ran up to 2x slower on the
            CPU and 4-5x on CUDA). ``"auto"``: compiled in
            float32 on the CPU when a C++ compiler is found (inductor needs one) and on CUDA
            when triton is found, else eager; each call layout is compiled only after
            :data:`~mmpc.solver.execution.AUTO_COMPILE_AFTER_S` of eager solving of it (``compile_after``). The
            environment variable ``MMPC_COMPILE=0`` makes it eager (``1``: compiled at once).
            Compiled, the first call of every new call layout (problems, goals, obstacle slots,
            same or mixed obstacle counts; per tile) runs twice: once to compile, once timed as
            a solve; :attr:`last_compile_ms` reports the first.
        tile_size: solve a batch of more than this many (problem, goal) elements as tiles of
            about this many, one call each: a power of two of whole problems per tile when a
            problem's goals fit (:func:`~mmpc.solver.execution.tiling`), else each problem's goals
            split evenly. The problems left over take one tile of the next power of two, padded
            with copies (dropped from the result), so that a few tile shapes are compiled.
            ``None``: 256 on the compiled CPU path, where it keeps a tile's working set in
            the L2 cache (~7 % faster at B = 1024), and no tiling elsewhere.
        compile_after: compiled, the estimated seconds of eager solving of a call layout (counted
            from its calls and sizes: deterministic) before the layout is compiled, so that a run
            too short to repay a compile stays eager. ``None``: :data:`~mmpc.solver.execution.AUTO_COMPILE_AFTER_S` for
            ``compile="auto"`` (without ``MMPC_COMPILE``), else 0 (compile at the first call).

    Attributes:
        last_compile_ms: wall time the last call spent compiling new call layouts [ms]; 0 when
            eager or when every layout had been compiled before.

    Shapes:
        see :class:`mmpc.ProblemBatch` (inputs) and :class:`mmpc.SolveResult` (outputs).

    Example:
        >>> import torch, mmpc
        >>> opt = mmpc.BatchOptimizer()
        >>> ego = mmpc.ego_state(0.0, 8.0, 0.0, 14.0)
        >>> goals = torch.tensor([[[120.0, 4.0], [120.0, 8.0]]])
        >>> obstacles = torch.zeros(1, 0, opt.config.num_steps, 2)
        >>> result = opt(mmpc.ProblemBatch(ego, goals, obstacles))
        >>> result.trajectories.x.shape, bool(result.feasible.all())
        (torch.Size([1, 2, 100]), True)
    """

    def __init__(
        self,
        config: Optional[OptimizerConfig] = None,
        *,
        dtype: torch.dtype = torch.float32,
        device: torch.device | str | None = None,
        compile: bool | str = False,
        tile_size: Optional[int] = None,
        compile_after: Optional[float] = None,
    ) -> None:
        super().__init__()
        if not dtype.is_floating_point:
            raise TypeError(f"`dtype` must be a floating dtype; got {dtype}")
        if tile_size is not None and (not isinstance(tile_size, int) or isinstance(tile_size, bool) or tile_size < 1):
            raise ValueError(f"`tile_size` must be None or an int >= 1 (elements per call); got {tile_size!r}")
        self.config = config if config is not None else OptimizerConfig()
        basis = bernstein_basis(self.config.order, self.config.num_steps, self.config.horizon)
        operators = build_operators(basis, self.config)
        for name, value in operators._asdict().items():
            self.register_buffer(name, value.to(dtype=dtype, device=device), persistent=False)
        self.register_buffer("times", basis.times.to(dtype=dtype, device=device), persistent=False)
        cfg = self.config
        heading = None if cfg.heading_target_deg is None else math.radians(cfg.heading_target_deg)
        on_cpu = torch.device(device or "cpu").type == "cpu"
        deferral = 0.0  # compile_after's default
        if compile == "auto":
            compile, deferral = execution.auto_compile(dtype == torch.float32, on_cpu)
        if not isinstance(compile, bool):
            raise ValueError(f"`compile` must be True, False or 'auto'; got {compile!r}")
        if compile_after is None:
            compile_after = deferral
        if isinstance(compile_after, bool) or not isinstance(compile_after, (int, float)) or not compile_after >= 0:
            raise ValueError(f"`compile_after` must be None or a number of seconds >= 0; got {compile_after!r}")
        self.compile_after = float(compile_after)
        self._eager_seconds: dict[tuple, float] = {}  # call layout -> estimated eager solving so far [s]
        # mmpc.solver.trig is exact to float32 rounding, not to float64's.
        polynomial_trig = compile and on_cpu and dtype == torch.float32
        self._limits = iterations.Limits(
            cfg.v_min, cfg.v_max, cfg.a_max - cfg.acceleration_backoff, heading, cfg.ellipse_a, cfg.ellipse_b,
            1.0 + cfg.obstacle_backoff, polynomial_trig=polynomial_trig,
        )
        self.compiled = compile
        self._eager_limits = self._limits._replace(polynomial_trig=False)  # for inputs that require grad
        self._fallback_logged = False
        self._limit_logged = False
        self.last_compile_ms = 0.0
        self._compiled_layouts: set[tuple] = set()
        if tile_size is None and compile and on_cpu:
            tile_size = execution.CPU_TILE_SIZE
        self.tile_size = tile_size
        self._graphs: OrderedDict[tuple, Optional[execution.GraphSolve]] = OrderedDict()  # CUDA: layout -> captured solve
        self._shifts: dict[float, torch.Tensor] = {}  # dt -> (K, K) transposed time shift of the coefficients
        self._functions = execution.EAGER
        self.chunk = self.config.iterations
        if compile:
            # Chunks of unrolled iterations: one compiled graph serves every chunk (the
            # operators are arguments), so compile time stays bounded while the per-call
            # overhead is paid once per chunk rather than once per iteration. On CUDA each
            # layout's whole solve is then captured as one CUDA graph (:meth:`_replay`).
            self.chunk = min(execution.COMPILED_CHUNK, self.config.iterations)
            self._functions = execution.compiled_functions(on_cpu)
            logger.info("BatchOptimizer: iterations compiled in chunks of %d", self.chunk)

    @property
    def dtype(self) -> torch.dtype:
        return self.samples.dtype

    @property
    def device(self) -> torch.device:
        return self.samples.device

    def shifted(self, warm: WarmStart, dt: float, start_offset: torch.Tensor) -> WarmStart:
        """``warm`` moved ``dt`` seconds along its trajectories (the last ``dt`` extrapolated) and
        to a start ``start_offset`` (E, 2) [m] from the old one: where the next control step's
        solve of the same goals can start (:meth:`forward`'s ``warm``)."""
        shift = self._shifts.get(dt)
        if shift is None:
            cfg = self.config
            shift = bernstein_shift(cfg.order, cfg.num_steps, cfg.horizon, dt).T.to(self.device, self.dtype).contiguous()
            self._shifts[dt] = shift
        position = warm.position @ shift - start_offset.to(self.dtype)[:, None, :, None]  # Bernstein weights sum to 1
        return WarmStart(position, warm.multipliers @ shift, warm.heading_multipliers @ shift)

    def forward(self, problem: ProblemBatch, *, history: bool = False, warm: Optional[WarmStart] = None,
                warm_iterations: Optional[int] = None, fixed_shapes: bool = False,
                cold_capacity: Optional[int] = None) -> SolveResult:
        """Solve every (problem, goal) element of ``problem``.

        Args:
            problem: the batch (see :class:`mmpc.ProblemBatch` for shapes and units).
            history: also return the residual norms after every iteration run.
            warm: start from these iterates (an earlier result's ``warm``, moved to this problem's
                start with :meth:`shifted`) instead of the cold start, and run only the last
                ``warm_iterations`` iterations of the penalty schedule. A problem with any
                iterate not finite (NaN marks a problem to restart, e.g. one new to the batch; inf
                a diverged solve), and one whose warm solve finds no feasible goal, solves from
                the cold start with the whole schedule, in a call of its own.
            warm_iterations: with ``warm``: iterations to run, 1 ... ``config.iterations``.
            fixed_shapes: solve without reading a value on the host, every shape known from the
                input shapes (what one graph of a whole decision needs, :meth:`_solve_fixed`): the
                values are not checked (a problem with NaN or inf comes out NUMERICAL, the others
                as they would), every problem takes its own obstacle-count operator, and a warm
                start runs on every problem, after which at most ``cold_capacity`` of them solve
                again cold. Needs ``config.exit_checks`` empty (an early exit is data-dependent).
            cold_capacity: with ``fixed_shapes`` and ``warm``: the problems solved again cold at
                most, 0 ... E (default E).

        Returns:
            A :class:`mmpc.SolveResult` with leading dims (E, G); with ``history`` and a warm
            start, a record per iteration of the schedule, NaN before a problem's first.

        Raises:
            TypeError: a non-tensor or non-floating input, or a non-bool mask.
            ValueError: a wrong shape or device, an empty batch, too many obstacle slots,
                NaN/inf in the ego state, the goals or a present obstacle, a negative speed; a warm
                start of other shapes or devices, or without ``warm_iterations`` in range.
        """
        self.last_compile_ms = 0.0
        if not isinstance(fixed_shapes, bool):
            raise TypeError(f"`fixed_shapes` must be True or False; got {fixed_shapes!r}")
        if fixed_shapes and self.config.exit_checks:
            raise ValueError(f"`fixed_shapes` needs an optimizer without early exits (a data-dependent batch); got "
                             f"exit_checks={self.config.exit_checks}")
        if cold_capacity is not None and (not fixed_shapes or warm is None):
            raise ValueError("`cold_capacity` applies to a warm start with `fixed_shapes=True`; got "
                             f"cold_capacity={cold_capacity!r}, fixed_shapes={fixed_shapes}, warm={'given' if warm is not None else None}")
        ego, goals, obstacles, mask, axes = checks.validate_problem(problem, self.config, self.dtype, self.device,
                                                                    values=not fixed_shapes)
        warm, first_iteration = checks.validate_warm(warm, warm_iterations, self.config, goals.shape[:2], self.dtype,
                                                     self.device)
        compiled = self.compiled
        if compiled and torch.is_grad_enabled() and any(t.requires_grad for t in (ego, goals, obstacles)):
            compiled = False  # the compiled graphs have no backward: autograd runs the eager functions
            if not self._fallback_logged:
                logger.info("BatchOptimizer: inputs require grad; solving eagerly, not compiled")
                self._fallback_logged = True
        if fixed_shapes:
            uniform = mask.shape[1] if problem.obstacle_mask is None else None
            return self._solve_fixed(ego, goals, obstacles, mask, axes, warm, first_iteration, history, compiled,
                                     uniform, cold_capacity)
        if warm is not None:
            return self._solve_warm(ego, goals, obstacles, mask, axes, warm, first_iteration, history, compiled)
        return self._solve_cold(ego, goals, obstacles, mask, axes, history, compiled)

    def _solve_fixed(self, ego: torch.Tensor, goals: torch.Tensor, obstacles: torch.Tensor, mask: torch.Tensor,
                     axes: Optional[torch.Tensor], warm: Optional[WarmStart], first_iteration: int, history: bool,
                     compiled: bool, uniform: Optional[int], cold_capacity: Optional[int]) -> SolveResult:
        """``forward(fixed_shapes=True)``: no host synchronisation. A warm start runs on every problem,
        those without finite iterates from a standstill (every iterate 0); then the problems that
        had no finite iterates or found no feasible goal, the first ``cold_capacity`` of them in
        row order (:func:`mmpc.compaction.compact`), solve again cold with the whole schedule. The
        others keep their warm answer (no feasible goal) and their iterates, so that they are in
        the next call's set again."""
        last = self.config.iterations
        if warm is None:
            return self._solve_compiled(ego, goals, obstacles, mask, axes, None, 0, last, history, compiled, uniform)
        num_problems = ego.shape[0]
        capacity = num_problems if cold_capacity is None else cold_capacity
        if isinstance(capacity, bool) or not isinstance(capacity, int) or not 0 <= capacity <= num_problems:
            raise ValueError(f"`cold_capacity` must be an int in [0, {num_problems}] (the problems); got {cold_capacity!r}")
        finite = warm.finite()
        start = WarmStart(*(torch.where(finite.view(-1, *(1,) * (field.dim() - 1)), field, 0.0) for field in warm))
        result = self._solve_compiled(ego, goals, obstacles, mask, axes, start, first_iteration, last, history, compiled,
                                      uniform)
        if capacity == 0:
            return result
        again = ~finite | ~result.feasible.any(dim=1)
        found = compact(again, capacity, fill=num_problems)
        (rows,) = found.index  # the padding: one past the last problem, a scratch row
        picked = rows.clamp(max=num_problems - 1)
        cold = self._solve_compiled(*_take_rows((ego, goals, obstacles, mask, axes), picked), None, 0, last, history,
                                    compiled, uniform)
        cold = cold._replace(iterations=cold.iterations + (last - first_iteration))  # and the warm run before
        return result.replace_rows(cold, rows)

    def _solve_cold(self, ego: torch.Tensor, goals: torch.Tensor, obstacles: torch.Tensor, mask: torch.Tensor,
                    axes: Optional[torch.Tensor], history: bool, compiled: bool) -> SolveResult:
        """From the cold start. With ``config.exit_checks``, the schedule runs in stretches between
        the checks: after each, the elements not yet :meth:`_settled` go on from their iterates, as
        a batch of one goal per problem (host synchronisations), and the others keep that iterate."""
        bounds = [*self.config.exit_checks, self.config.iterations]
        result = self._solve_compiled(ego, goals, obstacles, mask, axes, None, 0, bounds[0], history, compiled)
        if len(bounds) == 1:
            return result
        num_goals = goals.shape[1]
        running = (~self._settled(result)).flatten().nonzero().squeeze(1)  # flat (problem, goal) indices
        warm = WarmStart(*(field.flatten(0, 1)[running].unsqueeze(1) for field in result.warm))
        stretches = []  # (R, 1) results of the elements ``running`` had then, in its order, and those indices
        for first, last in zip(bounds[:-1], bounds[1:]):
            if running.numel() == 0:
                break
            rows, columns = running // num_goals, running % num_goals
            elements = (ego[rows], goals[rows, columns].unsqueeze(1), obstacles[rows], mask[rows],
                        None if axes is None else axes[rows])
            stretch = self._solve_compiled(*elements, warm, first, last, history, compiled)
            stretches.append((stretch._replace(iterations=stretch.iterations + first), running))
            going_on = ~self._settled(stretch)[:, 0]
            running, warm = running[going_on], WarmStart(*(field[going_on] for field in stretch.warm))
        for stretch, elements in stretches:  # later stretches overwrite the elements they ran on
            result = result.replace_elements(stretch, elements)
        return result

    def _settled(self, result: SolveResult) -> torch.Tensor:
        """(E, G) bool: feasible, and inside the sets the iterations project onto (the back-offs)
        up to the tolerances, where the rest of the schedule would aim: an early exit stops only
        these (a plan merely feasible early hugs the true constraints)."""
        cfg = self.config
        return (result.feasible
                & (result.min_obstacle_distance >= 1.0 + cfg.obstacle_backoff - cfg.obstacle_tolerance)
                & (result.max_acceleration <= cfg.a_max - cfg.acceleration_backoff + cfg.acceleration_tolerance))

    def _solve_warm(self, ego: torch.Tensor, goals: torch.Tensor, obstacles: torch.Tensor, mask: torch.Tensor,
                    axes: Optional[torch.Tensor], warm: WarmStart, first_iteration: int, history: bool,
                    compiled: bool) -> SolveResult:
        """A warm-started batch: the problems with finite iterates from them; those without, and
        those whose warm solve found no feasible goal (what a cold start may still find), from the
        cold start with the whole schedule; joined in the input order (host synchronisations)."""
        inputs = (ego, goals, obstacles, mask, axes)
        cold = ~warm.finite()
        again = torch.zeros_like(cold)  # warm-started, no feasible goal: solved again cold
        parts, solved = [], []
        warm_rows = (~cold).nonzero().squeeze(1)
        if warm_rows.numel():
            part = self._solve_compiled(*_take_rows(inputs, warm_rows), warm.take(warm_rows), first_iteration,
                                        self.config.iterations, history, compiled)
            parts.append(part)
            solved.append(warm_rows)
            again[warm_rows] = ~part.feasible.any(dim=1)
        cold_rows = (cold | again).nonzero().squeeze(1)
        if cold_rows.numel():
            part = self._solve_cold(*_take_rows(inputs, cold_rows), history, compiled)
            warm_run = again[cold_rows, None].int() * (self.config.iterations - first_iteration)
            parts.append(part._replace(iterations=part.iterations + warm_run))  # replaces the warm answer of those
            solved.append(cold_rows)
        if len(parts) == 1 and solved[0].numel() == ego.shape[0]:
            return parts[0]
        return SolveResult.interleave(parts, solved, ego.shape[0])

    def _solve_compiled(self, ego: torch.Tensor, goals: torch.Tensor, obstacles: torch.Tensor, mask: torch.Tensor,
                        axes: Optional[torch.Tensor], warm: Optional[WarmStart], first_iteration: int,
                        last_iteration: int, history: bool, compiled: bool,
                        uniform: Optional[int] | str = "find") -> SolveResult:
        """:meth:`_solve_batch` of the schedule's iterations ``first_iteration`` up to ``last_iteration``
        within the compiled path's recompile limit (eager past it)."""
        span = (first_iteration, last_iteration)
        if not compiled:
            return self._solve_batch(ego, goals, obstacles, mask, axes, warm, span, history, compiled, uniform)
        # Every call layout (problems x goals per tile, obstacle slots) is a recompile of the same
        # functions, shared by every optimizer of the process: one driver mixing goal counts (a
        # proposer and its escalations) or several scenarios in one worker pass torch's default
        # limit of 8, where a fullgraph compile fails hard.
        try:
            with torch._dynamo.config.patch(recompile_limit=execution.RECOMPILE_LIMIT):
                return self._solve_batch(ego, goals, obstacles, mask, axes, warm, span, history, compiled, uniform)
        except torch._dynamo.exc.FailOnRecompileLimitHit:
            if not self._limit_logged:
                logger.warning("BatchOptimizer: %d compiled call layouts in this process (the limit); new layouts "
                               "solve eagerly", execution.RECOMPILE_LIMIT)
                self._limit_logged = True
            self.last_compile_ms = 0.0
            return self._solve_batch(ego, goals, obstacles, mask, axes, warm, span, history, False, uniform)

    def _solve_batch(self, ego: torch.Tensor, goals: torch.Tensor, obstacles: torch.Tensor, mask: torch.Tensor,
                     axes: Optional[torch.Tensor], warm: Optional[WarmStart], span: tuple[int, int], history: bool,
                     compiled: bool, uniform: Optional[int] | str = "find") -> SolveResult:
        """:meth:`forward` on validated inputs: one call, or tiles of :attr:`tile_size` elements; ``span``:
        the schedule's iterations run, (first, end); ``uniform``: as :meth:`_prepare`'s."""
        num_problems, num_goals = goals.shape[:2]
        tiling = execution.tiling(num_problems, num_goals, self.tile_size)
        if tiling is None:
            bucket = num_problems
            if compiled:
                on_cpu = self.device.type == "cpu"
                bucket = (execution.problem_bucket(num_problems, num_goals, self.tile_size) if on_cpu
                          else execution.graph_bucket(num_problems))
            if bucket == num_problems:
                return self._solve(ego, goals, obstacles, mask, axes, warm, span, history, compiled, uniform)
            inputs = (ego, goals, obstacles, mask, axes)
            ego, goals, obstacles, mask, axes = (execution.repeat_last(t, 0, bucket) for t in inputs)
            warm = execution.repeat_warm(warm, 0, bucket)
            result = self._solve(ego, goals, obstacles, mask, axes, warm, span, history, compiled, uniform)
            return result.head(num_problems, num_goals)
        tile_problems, tile_goals = tiling
        tiles = execution.problem_tiles(num_problems, tile_problems)
        # Pad both axes to the tiles with copies of the last problem / goal.
        padded_problems = tiles[-1][0] + tiles[-1][1]
        inputs = (ego, goals, obstacles, mask, axes)
        ego, goals, obstacles, mask, axes = (execution.repeat_last(t, 0, padded_problems) for t in inputs)
        padded_goals = execution.ceil_div(num_goals, tile_goals) * tile_goals
        goals = execution.repeat_last(goals, 1, padded_goals)
        warm = execution.repeat_warm(execution.repeat_warm(warm, 0, padded_problems), 1, padded_goals)
        bands = []
        for first, count in tiles:
            problems = slice(first, first + count)
            tile_axes = None if axes is None else axes[problems]
            band = [
                self._solve(
                    ego[problems], goals[problems, g : g + tile_goals], obstacles[problems], mask[problems], tile_axes,
                    None if warm is None else WarmStart(*(field[problems, g : g + tile_goals] for field in warm)),
                    span, history, compiled, uniform,
                )
                for g in range(0, goals.shape[1], tile_goals)
            ]
            bands.append(SolveResult.concatenate(band, dim=1))
        return SolveResult.concatenate(bands, dim=0).head(num_problems, num_goals)

    def _solve(
        self,
        ego: torch.Tensor,
        goals: torch.Tensor,
        obstacles: torch.Tensor,
        mask: torch.Tensor,
        axes: Optional[torch.Tensor],
        warm: Optional[WarmStart],
        span: tuple[int, int],
        history: bool,
        compiled: bool,
        uniform: Optional[int] | str = "find",
    ) -> SolveResult:
        """One call of the iterations on validated inputs (shapes as in :class:`mmpc.ProblemBatch`);
        compiled, a call layout solves eagerly until :attr:`compile_after` is spent on it, and a
        new one is then run once untimed first (see :attr:`last_compile_ms`); ``uniform``: as
        :meth:`_prepare`'s."""
        if compiled and uniform == "find":
            counts = mask.sum(dim=1).unique()  # a host synchronisation: the operators differ per obstacle count
            uniform = int(counts[0]) if counts.numel() == 1 else None
        if compiled:
            # A cold and a warm solve of one shape share every compiled function (the cold start is
            # resumed from its iterates), so a layout is the shape and the chunk lengths the span runs.
            chunks = tuple(sorted({min(self.chunk, span[1] - first) for first in range(*span, self.chunk)}))
            layout = (*goals.shape[:2], mask.shape[1], uniform is None, axes is None, chunks)
            share = (span[1] - span[0]) / self.config.iterations
            compiled = not self._deferred(layout, goals.shape[0] * goals.shape[1] * share)
        if compiled and self.device.type == "cuda":
            return self._replay(ego, goals, obstacles, mask, axes, warm, span, history, uniform)
        start = time.perf_counter() if compiled else 0.0
        # compiles the input layout too
        prepared = self._prepare(ego, goals, obstacles, mask, axes, compiled, uniform=uniform, warm=warm, span=span)
        if compiled and layout not in self._compiled_layouts:
            self._run(prepared, history)
            self.last_compile_ms += (time.perf_counter() - start) * 1e3
            self._compiled_layouts.add(layout)
        return self._run(prepared, history)

    def _deferred(self, layout: tuple, elements: float) -> bool:
        """Whether this call of ``layout`` solves eagerly: less than :attr:`compile_after` seconds
        of eager solving of it estimated so far (from call counts and sizes, not clocks, so that a
        run's episodes are the same however loaded the machine); ``elements``: the call's (problem,
        goal) elements times the share of the schedule it runs."""
        spent = self._eager_seconds.get(layout, 0.0)
        if spent >= self.compile_after:
            return False
        fixed, per_element = execution.EAGER_SECONDS[self.device.type == "cuda"]
        self._eager_seconds[layout] = spent + fixed + per_element * elements
        return True

    def _replay(self, ego: torch.Tensor, goals: torch.Tensor, obstacles: torch.Tensor, mask: torch.Tensor,
                axes: Optional[torch.Tensor], warm: Optional[WarmStart], span: tuple[int, int], history: bool,
                uniform: Optional[int]) -> SolveResult:
        """Compiled CUDA path: the call layout's whole solve (layout, cold or warm start, iterations,
        outputs) replayed as one CUDA graph, captured at its first call; the result is copied out
        of the graph's memory, so a later solve leaves it intact. A layout whose capture fails
        runs the compiled functions without a graph (warned once); ``uniform``: every problem's
        obstacle count, ``None`` where they differ."""
        key = (tuple(goals.shape), mask.shape[1], uniform, axes is None, history, span)
        inputs = (ego, goals, obstacles, mask, axes, *(warm if warm is not None else (None,) * len(WarmStart._fields)))
        solve = functools.partial(self._solve_prepared, uniform=uniform, history=history, span=span)
        if key not in self._graphs:
            start = time.perf_counter()
            self._graphs[key] = execution.GraphSolve.capture(solve, inputs)
            self.last_compile_ms += (time.perf_counter() - start) * 1e3
            if len(self._graphs) > execution.GRAPH_CACHE:
                self._graphs.popitem(last=False)  # frees the oldest graph's memory pool
        self._graphs.move_to_end(key)
        graph = self._graphs[key]
        if graph is None:
            return solve(*inputs)
        return graph.replay(inputs)

    def _solve_prepared(self, ego: torch.Tensor, goals: torch.Tensor, obstacles: torch.Tensor, mask: torch.Tensor,
                        axes: Optional[torch.Tensor], *warm: Optional[torch.Tensor], uniform: Optional[int], history: bool,
                        span: tuple[int, int]) -> SolveResult:
        """The compiled functions on one call whose obstacle-count layout (``uniform``) is known,
        from the cold start or from ``warm``'s fields at ``span[0]``: no host
        synchronisation, so that a CUDA graph can capture it."""
        start = None if warm[0] is None else WarmStart(*warm)
        prepared = self._prepare(ego, goals, obstacles, mask, axes, True, uniform=uniform, warm=start, span=span)
        return self._run(prepared, history)

    def _run(self, prepared: iterations.Prepared, history: bool) -> SolveResult:
        """The cold start, the iterations and the outputs of one prepared call."""
        functions, limits = self._functions, self._limits
        if not prepared.compiled:
            functions, limits = execution.EAGER, self._eager_limits
        if prepared.warm is None:
            start = iterations.cold_iterates(prepared.b_position, self.position_init, prepared.obstacles.shape[3])
        else:
            start = prepared.warm
        gather = self.gather[max(prepared.first_iteration - 1, 0)]
        state = functions.resume(*start, prepared.obstacles, prepared.axes, self.samples, gather, limits)
        records: list[torch.Tensor] = []
        for first in range(prepared.first_iteration, prepared.last_iteration, self.chunk):
            last = min(first + self.chunk, prepared.last_iteration)
            if prepared.uniform_count is not None:
                position = self.position[first:last, prepared.uniform_count]  # (U, 2, K, D)
            else:
                position = self.position[first:last].index_select(1, prepared.counts)  # (U, E, 2, K, D)
            state, step = functions.iterate(
                state, prepared.b_position, prepared.b_heading, prepared.obstacles, prepared.axes, position,
                self.gather[first:last], self.heading[first:last], self.heading_gather[first:last],
                self.samples, self.heading_basis, limits, history,
            )
            records.extend(step.records)
        num_goals = prepared.num_goals - prepared.padding
        fields, coefficients, norms, scalars, status = functions.summarise(
            state.c, step, prepared.obstacles, prepared.axes, prepared.mask, prepared.origin, prepared.goal_ahead, num_goals,
            self.heading_basis, self.heading_rate_basis, self.config, limits,
        )
        history_norms = None
        if history:  # NaN: the iterations of the schedule this call did not run
            ran = torch.nan_to_num(torch.stack(records)[:, :, :num_goals], nan=float("inf"))
            history_norms = ran.new_full((self.config.iterations, *ran.shape[1:]), float("nan"))
            history_norms[prepared.first_iteration : prepared.last_iteration] = ran
        num_problems, order = prepared.obstacles.shape[3], state.c.shape[0]
        warm = WarmStart(  # views of the final iterates in the batch-first layout, padding goals dropped
            state.c.view(order, 2, num_problems, -1)[..., :num_goals].permute(2, 3, 1, 0),
            state.multipliers.view(order, 2, num_problems, -1)[..., :num_goals].permute(2, 3, 1, 0),
            state.multipliers_psi.view(order, num_problems, -1)[..., :num_goals].permute(1, 2, 0),
        )
        return SolveResult(
            trajectories=Trajectories(self.times, *fields),
            coefficients=coefficients,
            residual_obstacle=norms[..., 0],
            residual_acceleration=norms[..., 1],
            residual_nonholonomic=norms[..., 2],
            min_obstacle_distance=scalars[0],
            max_heading_deviation=scalars[1],
            max_acceleration=scalars[2],
            max_nonholonomic_error=scalars[3],
            status=status,
            feasible=status == 0,
            iterations=torch.full_like(status, prepared.last_iteration - prepared.first_iteration),
            history=history_norms,
            warm=warm,
        )

    # ----------------------------------------------------------------------------- inputs

    def _prepare(
        self, ego: torch.Tensor, goals: torch.Tensor, obstacles: torch.Tensor, mask: torch.Tensor,
        axes: Optional[torch.Tensor], compiled: bool, *, uniform: Optional[int] | str = "find",
        warm: Optional[WarmStart] = None, span: Optional[tuple[int, int]] = None,
    ) -> iterations.Prepared:
        """The solver layout of one call; ``uniform``: the obstacle count every problem has
        (``None``: counts differ), or ``"find"`` to read it from the mask (a host synchronisation);
        ``warm``: iterates to start from, at iteration ``span[0]``; the schedule runs up to ``span[1]``
        (``None``: all of it)."""
        cfg = self.config
        span = (0, cfg.iterations) if span is None else span
        padding = 0
        if compiled and self.device.type == "cpu":
            padding = execution.goal_padding(goals.shape[0], goals.shape[1], goals.element_size())
            goals = execution.repeat_last(goals, 1, goals.shape[1] + padding)
            warm = execution.repeat_warm(warm, 1, goals.shape[1])
        layout = (self._functions if compiled else execution.EAGER).layout
        origin, b_position, b_heading, obstacles, axes, goal_ahead, counts = layout(
            ego, goals, obstacles, mask, axes, cfg.start_acceleration, (cfg.ellipse_a, cfg.ellipse_b), cfg.a_max
        )
        if uniform == "find":
            count_values = counts.unique()
            uniform = int(count_values[0]) if count_values.numel() == 1 else None
        return iterations.Prepared(
            origin=origin,
            b_position=b_position,
            b_heading=b_heading,
            obstacles=obstacles,
            axes=axes,
            mask=mask,
            counts=counts,
            uniform_count=uniform,
            goal_ahead=goal_ahead,
            num_goals=goals.shape[1],
            padding=padding,
            compiled=compiled,
            warm=None if warm is None else iterations.solver_layout(warm),
            first_iteration=span[0],
            last_iteration=span[1],
        )


def _take_rows(tensors: tuple[Optional[torch.Tensor], ...], rows: torch.Tensor) -> tuple[Optional[torch.Tensor], ...]:
    """The problems ``rows`` of each tensor (``None`` stays ``None``)."""
    return tuple(None if t is None else t[rows] for t in tensors)
