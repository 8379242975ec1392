"""The batch non-holonomic trajectory optimizer (alternating minimisation, Adajania et al. 2022).

One iteration, for every (problem, goal) element at once:

1. position QP (x and y): one cached KKT operator times ``[c, u, lambda, b]``;
2. heading QP: pull ``psi = P c_psi`` towards ``atan2(ydot, xdot)`` (clipped to the heading band
   when ``config.heading_target_deg`` is set); cached operator;
   ``lambda_psi -= rho P^T (psi - atan2(ydot, xdot))`` (the sign that converges; the paper's
   printed update has it reversed);
3. speed: ``v = clip((xdot, ydot) . (cos psi, sin psi), v_min, v_max)`` — the projection on the
   heading, which minimises the non-holonomic penalty for fixed psi (the paper uses the norm);
4. obstacles: every trajectory point is projected radially out of every ellipse — the closed
   forms of alpha and d = max(1, r) without trigonometry; only the push summed over the
   obstacles leaves the step (compiled, the (M, N, E, G) offsets are never stored);
5. acceleration: projected onto the disc of radius a_max — the closed forms of alpha_a, d_a;
6. ``lambda -= rho F^T (F c - g)``, with the residual mapped to coefficient space once and
   reused by the next position QP.

There is no Python branching on tensor values and no host synchronisation inside the loop.
Compiled for the CPU in float32, the iterations take sin, cos and atan2 from :mod:`mmpc.trig`
(short polynomials the compiler fuses into the loops, float32-exact for headings below 1e4 rad);
compiled for the CPU they contract multiply-adds; eager, in float64 and on the GPU they use the
torch functions.
"""

from __future__ import annotations

import functools
import logging
import math
import os
import time
from collections import OrderedDict
from typing import NamedTuple, Optional

import torch
from torch import nn

from mmpc import trig
from mmpc.basis import bernstein_basis, bernstein_shift
from mmpc.config import OptimizerConfig
from mmpc.operators import build_operators
from mmpc.problem import EGO_A, EGO_FIELDS, EGO_PSI, EGO_PSIDOT, EGO_V, EGO_X, EGO_Y, ProblemBatch
from mmpc.result import SolveResult, Status, Trajectories, WarmStart

logger = logging.getLogger(__name__)

#: Where absent obstacle slots are parked, relative to the ego [m]: far enough that no
#: trajectory point is ever inside their ellipse, small enough to square in float32.
_PARKED_DISTANCE = 1.0e5
_EPS_SQUARED = 1.0e-12
#: Iterations per compiled graph in the ``compile=True`` path.
_COMPILED_CHUNK = 10
#: Environment variable that decides ``compile="auto"`` (what :func:`mmpc.scenario.build_mpc`
#: passes): ``0`` eager, ``1`` compiled at once, unset: compiled in float32 where a kernel
#: compiler is found, each call layout once its eager solving would have cost
#: :data:`AUTO_COMPILE_AFTER_S`. Read in one place, :func:`_auto_compile`; the command line's
#: ``--compile auto|on|off`` sets it (:func:`mmpc.cli.arguments.apply_compile`), so that worker
#: processes inherit the choice. Compiling is a run option, not part of a scenario.
COMPILE_ENV = "MMPC_COMPILE"
#: Widest SIMD register the compiled CPU kernels use (AVX-512) [bytes].
_SIMD_BYTES = 64
#: Recompiles of each compiled function a process allows (torch's default: 8): one per call layout
#: (the CPU kernels are shape-specialised); past it, new layouts solve eagerly.
_RECOMPILE_LIMIT = 256

#: ``compile="auto"``: estimated seconds of eager solving of a call layout before it is compiled.
#: Compiling a layout takes 10-60 s, so a run that would not repay it (one ``mmpc drive`` episode:
#: ~12 s of solving) stays eager, and a long one pays at most this much more than compiling at once.
AUTO_COMPILE_AFTER_S = 20.0
#: Eager seconds per call (fixed, per (problem, goal) element of the whole schedule): CPU (one thread), CUDA; from
#: ``scripts/bench_solver.py`` (CPU: 13.6 ms at B = 1, 2.76 s at B = 4096; H100: ~60 ms to B = 4096).
_EAGER_SECONDS = {False: (0.013, 0.67e-3), True: (0.06, 5e-6)}

#: Captured CUDA graphs an optimizer keeps (least recently used dropped first): each holds its own memory.
_GRAPH_CACHE = 16

#: Elements per call of the compiled CPU path: a tile's (3N, 2, tile) samples and residuals
#: (~0.6 MB in float32) stay in a core's L2 cache between the products and the fused steps.
_CPU_TILE_SIZE = 256


class _Residuals(NamedTuple):
    """Closed-form steps of one iteration. Layout: batch last, columns ordered (axis, e, g)."""

    stacked: torch.Tensor  # (3N, 2, E, G) [obstacle push; acceleration residual; velocity residual]
    speed: torch.Tensor  # (N, E, G) v [m/s]


class _Prepared(NamedTuple):
    """Validated inputs in the ego-relative frame, in the module's dtype and solver layout."""

    origin: torch.Tensor  # (E, 2) ego start position [m]
    b_position: torch.Tensor  # (n_eq, 2 E G') boundary values of x and y
    b_heading: torch.Tensor  # (4, E G') boundary values of psi
    obstacles: torch.Tensor  # (M, N, 2, E, 1) obstacle centres / semi-axes, absent slots parked
    axes: Optional[torch.Tensor]  # (M, 1, 4, E, 1) per-obstacle semi-axes a, b [m] and 1/a, 1/b; None: the config's
    mask: torch.Tensor  # (E, M) bool
    counts: torch.Tensor  # (E,) int64 number of present obstacles
    uniform_count: Optional[int]  # the count when it is the same for every problem
    goal_ahead: torch.Tensor  # (E, G') bool
    num_goals: int  # G', the goals solved for: the G given and `padding` copies of the last
    padding: int  # goals appended to fill SIMD vectors (compiled CPU path), dropped from the result
    compiled: bool  # run the compiled functions; False: the eager ones (autograd)
    warm: Optional[tuple[torch.Tensor, torch.Tensor, torch.Tensor]]  # (K, 2B), (K, 2B), (K, B) iterates to start from
    first_iteration: int  # the first iteration of the schedule run: 0 from the cold start
    last_iteration: int  # the schedule runs up to (not including) this iteration


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
            the CPU the cold start and the outputs are compiled too, C++ wrappers call the
            kernels, and a small batch is padded with copies of its last goal to whole SIMD
            vectors (the copies are dropped from the result). On CUDA every call layout's whole
            solve is captured once as a CUDA graph and replayed (E rounded up to a few sizes per
            octave, :func:`_graph_bucket`); results are copied out of the graph. Eager (the
            default) is the reference and supports autograd
            everywhere: a compiled optimizer solves inputs that require grad (autograd enabled)
            eagerly, with torch's sin, cos and atan2 (the same values to float32 rounding), as
            its compiled graphs are not differentiated. On the CPU every call layout gets its
            own shape-specialised kernels (a few seconds to compile each, 10-30 s on CUDA; torch's
            dynamic-shape kernels, its default from a second shape on, ran up to 2x slower on the
            CPU and 4-5x on CUDA). ``"auto"``: compiled in
            float32 on the CPU when a C++ compiler is found (inductor needs one) and on CUDA
            when triton is found, else eager; each call layout is compiled only after
            :data:`AUTO_COMPILE_AFTER_S` of eager solving of it (``compile_after``). The
            environment variable ``MMPC_COMPILE=0`` makes it eager (``1``: compiled at once).
            Compiled, the first call of every new call layout (problems, goals, obstacle slots,
            same or mixed obstacle counts; per tile) runs twice: once to compile, once timed as
            a solve; :attr:`last_compile_ms` reports the first.
        tile_size: solve a batch of more than this many (problem, goal) elements as tiles of
            at most this many, one call each: whole problems per tile when a problem's goals
            fit, else each problem's goals split evenly. The last tile is padded with copies
            (dropped from the result) so that every tile has one shape, compiled once.
            ``None``: 256 on the compiled CPU path, where it keeps a tile's working set in
            the L2 cache (~7 % faster at B = 1024), and no tiling elsewhere.
        compile_after: compiled, the estimated seconds of eager solving of a call layout (counted
            from its calls and sizes: deterministic) before the layout is compiled, so that a run
            too short to repay a compile stays eager. ``None``: :data:`AUTO_COMPILE_AFTER_S` for
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
            compile, deferral = _auto_compile(dtype == torch.float32, on_cpu)
        if not isinstance(compile, bool):
            raise ValueError(f"`compile` must be True, False or 'auto'; got {compile!r}")
        if compile_after is None:
            compile_after = deferral
        if isinstance(compile_after, bool) or not isinstance(compile_after, (int, float)) or not compile_after >= 0:
            raise ValueError(f"`compile_after` must be None or a number of seconds >= 0; got {compile_after!r}")
        self.compile_after = float(compile_after)
        self._eager_seconds: dict[tuple, float] = {}  # call layout -> estimated eager solving so far [s]
        # mmpc.trig is exact to float32 rounding, not to float64's.
        polynomial_trig = compile and on_cpu and dtype == torch.float32
        self._limits = _Limits(
            cfg.v_min, cfg.v_max, cfg.a_max - cfg.acceleration_backoff, heading, cfg.ellipse_a, cfg.ellipse_b,
            1.0 + cfg.obstacle_backoff, polynomial_trig=polynomial_trig,
        )
        self.compiled = compile
        self._eager_limits = self._limits._replace(polynomial_trig=False)  # for inputs that require grad
        self._fallback_logged = False
        self._limit_logged = False
        self.last_compile_ms = 0.0
        self._compiled_layouts: set[tuple[int, int, int, bool, bool]] = set()
        if tile_size is None and compile and on_cpu:
            tile_size = _CPU_TILE_SIZE
        self.tile_size = tile_size
        self._graphs: OrderedDict[tuple, Optional[_GraphSolve]] = OrderedDict()  # CUDA: layout -> captured solve
        self._shifts: dict[float, torch.Tensor] = {}  # dt -> (K, K) transposed time shift of the coefficients
        self._layout, self._start, self._resume, self._summarise, self._iterate = _layout, _start, _resume, _summarise, _iterate
        self.chunk = self.config.iterations
        if compile:
            # Chunks of unrolled iterations: one compiled graph serves every chunk (the
            # operators are arguments), so compile time stays bounded while the per-call
            # overhead is paid once per chunk rather than once per iteration.
            self.chunk = min(_COMPILED_CHUNK, self.config.iterations)
            if not on_cpu:
                # Fused triton kernels, specialised to each call layout's shapes (dynamic ones,
                # compiled at a small batch, ran 4-5x slower at large ones); each layout's whole
                # solve is then captured as one CUDA graph (:meth:`_replay`): one launch per solve.
                compile_cuda = functools.partial(torch.compile, fullgraph=True, dynamic=False)
                self._layout = compile_cuda(_layout)
                self._start = compile_cuda(_start)
                self._resume = compile_cuda(_resume)
                self._summarise = compile_cuda(_summarise)
                self._iterate = compile_cuda(_iterate)
            else:
                # A C++ wrapper calls the kernels, without Python between them; the layout, the cold start
                # and the outputs are compiled too (at small batch their eager op-by-op
                # dispatch would cost as much as the iterations). Multiply-adds contract to
                # fused multiply-adds (one rounding instead of two).
                options = {"cpp_wrapper": True, "cpp.enable_floating_point_contract_flag": "fast"}
                compile_cpu = functools.partial(torch.compile, fullgraph=True, dynamic=False, options=options)
                self._layout = compile_cpu(_layout)
                self._start = compile_cpu(_start)
                self._resume = compile_cpu(_resume)
                self._summarise = compile_cpu(_summarise)
                self._iterate = compile_cpu(_iterate)
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
                warm_iterations: Optional[int] = None) -> SolveResult:
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
        ego, goals, obstacles, mask, axes = _validate(problem, self.config, self.dtype, self.device)
        warm, first_iteration = _validate_warm(warm, warm_iterations, self.config, goals.shape[:2], self.dtype, self.device)
        compiled = self.compiled
        if compiled and torch.is_grad_enabled() and any(t.requires_grad for t in (ego, goals, obstacles)):
            compiled = False  # the compiled graphs have no backward: autograd runs the eager functions
            if not self._fallback_logged:
                logger.info("BatchOptimizer: inputs require grad; solving eagerly, not compiled")
                self._fallback_logged = True
        if warm is not None:
            return self._solve_warm(ego, goals, obstacles, mask, axes, warm, first_iteration, history, compiled)
        return self._solve_cold(ego, goals, obstacles, mask, axes, history, compiled)

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
            # Whole tiles, then the rest (padded to a power of two): the tiler would pad every tile.
            parts = []
            for piece in torch.arange(running.numel(), device=running.device).split(self.tile_size or running.numel()):
                rows, columns = running[piece] // num_goals, running[piece] % num_goals
                elements = (ego[rows], goals[rows, columns].unsqueeze(1), obstacles[rows], mask[rows],
                            None if axes is None else axes[rows])
                parts.append(self._solve_compiled(*elements, WarmStart(*(field[piece] for field in warm)), first, last,
                                                  history, compiled))
            stretch = SolveResult.concatenate(parts, dim=0)
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
        cold = ~torch.stack([field.isfinite().flatten(1).all(dim=1) for field in warm]).all(dim=0)  # (E,)
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
                        last_iteration: int, history: bool, compiled: bool) -> SolveResult:
        """:meth:`_solve_batch` of the schedule's iterations ``first_iteration`` up to ``last_iteration``
        within the compiled path's recompile limit (eager past it)."""
        span = (first_iteration, last_iteration)
        if not compiled:
            return self._solve_batch(ego, goals, obstacles, mask, axes, warm, span, history, compiled)
        # Every call layout (problems x goals per tile, obstacle slots) is a recompile of the same
        # functions, shared by every optimizer of the process: one driver mixing goal counts (a
        # proposer and its escalations) or several scenarios in one worker pass torch's default
        # limit of 8, where a fullgraph compile fails hard.
        try:
            with torch._dynamo.config.patch(recompile_limit=_RECOMPILE_LIMIT):
                return self._solve_batch(ego, goals, obstacles, mask, axes, warm, span, history, compiled)
        except torch._dynamo.exc.FailOnRecompileLimitHit:
            if not self._limit_logged:
                logger.warning("BatchOptimizer: %d compiled call layouts in this process (the limit); new layouts "
                               "solve eagerly", _RECOMPILE_LIMIT)
                self._limit_logged = True
            self.last_compile_ms = 0.0
            return self._solve_batch(ego, goals, obstacles, mask, axes, warm, span, history, False)

    def _solve_batch(self, ego: torch.Tensor, goals: torch.Tensor, obstacles: torch.Tensor, mask: torch.Tensor,
                     axes: Optional[torch.Tensor], warm: Optional[WarmStart], span: tuple[int, int], history: bool,
                     compiled: bool) -> SolveResult:
        """:meth:`forward` on validated inputs: one call, or tiles of :attr:`tile_size` elements; ``span``:
        the schedule's iterations run, (first, end)."""
        num_problems, num_goals = goals.shape[:2]
        tiling = _tiling(num_problems, num_goals, self.tile_size)
        if tiling is None:
            bucket = num_problems
            if compiled:
                on_cpu = self.device.type == "cpu"
                bucket = _problem_bucket(num_problems, num_goals, self.tile_size) if on_cpu else _graph_bucket(num_problems)
            if bucket == num_problems:
                return self._solve(ego, goals, obstacles, mask, axes, warm, span, history, compiled)
            ego, goals, obstacles, mask, axes = (_repeat_last(t, 0, bucket) for t in (ego, goals, obstacles, mask, axes))
            warm = _repeat_warm(warm, 0, bucket)
            result = self._solve(ego, goals, obstacles, mask, axes, warm, span, history, compiled)
            return result.head(num_problems, num_goals)
        tile_problems, tile_goals = tiling
        # Pad both axes to whole tiles with copies of the last problem / goal.
        padded_problems = _ceil_div(num_problems, tile_problems) * tile_problems
        ego, goals, obstacles, mask, axes = (_repeat_last(t, 0, padded_problems) for t in (ego, goals, obstacles, mask, axes))
        padded_goals = _ceil_div(num_goals, tile_goals) * tile_goals
        goals = _repeat_last(goals, 1, padded_goals)
        warm = _repeat_warm(_repeat_warm(warm, 0, padded_problems), 1, padded_goals)
        bands = []
        for row in range(0, padded_problems, tile_problems):
            problems = slice(row, row + tile_problems)
            tile_axes = None if axes is None else axes[problems]
            tiles = [
                self._solve(
                    ego[problems], goals[problems, g : g + tile_goals], obstacles[problems], mask[problems], tile_axes,
                    None if warm is None else WarmStart(*(field[problems, g : g + tile_goals] for field in warm)),
                    span, history, compiled,
                )
                for g in range(0, goals.shape[1], tile_goals)
            ]
            bands.append(SolveResult.concatenate(tiles, dim=1))
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
    ) -> SolveResult:
        """One call of the iterations on validated inputs (shapes as in :class:`mmpc.ProblemBatch`);
        compiled, a call layout solves eagerly until :attr:`compile_after` is spent on it, and a
        new one is then run once untimed first (see :attr:`last_compile_ms`)."""
        uniform: Optional[int] | str = "find"
        if compiled:
            counts = mask.sum(dim=1).unique()  # a host synchronisation: the operators differ per obstacle count
            uniform = int(counts[0]) if counts.numel() == 1 else None
            layout = (*goals.shape[:2], mask.shape[1], uniform is None, axes is None, span)
            share = (span[1] - span[0]) / self.config.iterations
            compiled = not self._deferred(layout, goals.shape[0] * goals.shape[1] * share)
        if compiled and self.device.type == "cuda":
            return self._replay(ego, goals, obstacles, mask, axes, warm, span, history, uniform)
        start = time.perf_counter()
        # compiles the input layout too
        prepared = self._prepare(ego, goals, obstacles, mask, axes, compiled, uniform=uniform, warm=warm, span=span)
        if compiled:
            if layout not in self._compiled_layouts:
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
        fixed, per_element = _EAGER_SECONDS[self.device.type == "cuda"]
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
            self._graphs[key] = _GraphSolve.capture(solve, inputs)
            self.last_compile_ms += (time.perf_counter() - start) * 1e3
            if len(self._graphs) > _GRAPH_CACHE:
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


    def _run(self, prepared: _Prepared, history: bool) -> SolveResult:
        """The cold start, the iterations and the outputs of one prepared call."""
        start, resume, iterate, summarise = self._start, self._resume, self._iterate, self._summarise
        limits = self._limits
        if not prepared.compiled:
            start, resume, iterate, summarise, limits = _start, _resume, _iterate, _summarise, self._eager_limits
        if prepared.warm is None:
            state = start(prepared.b_position, prepared.obstacles, prepared.axes, self.position_init, self.samples,
                          self.gather[0], limits)
        else:
            gather = self.gather[max(prepared.first_iteration - 1, 0)]
            state = resume(*prepared.warm, prepared.obstacles, prepared.axes, self.samples, gather, limits)
        records: list[torch.Tensor] = []
        for first in range(prepared.first_iteration, prepared.last_iteration, self.chunk):
            last = min(first + self.chunk, prepared.last_iteration)
            if prepared.uniform_count is not None:
                position = self.position[first:last, prepared.uniform_count]  # (U, 2, K, D)
            else:
                position = self.position[first:last].index_select(1, prepared.counts)  # (U, E, 2, K, D)
            state, step = iterate(
                state, prepared.b_position, prepared.b_heading, prepared.obstacles, prepared.axes, position,
                self.gather[first:last], self.heading[first:last], self.heading_gather[first:last],
                self.samples, self.heading_basis, limits, history,
            )
            records.extend(step.records)
        num_goals = prepared.num_goals - prepared.padding
        fields, coefficients, norms, scalars, status = summarise(
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
    ) -> _Prepared:
        """The solver layout of one call; ``uniform``: the obstacle count every problem has
        (``None``: counts differ), or ``"find"`` to read it from the mask (a host synchronisation);
        ``warm``: iterates to start from, at iteration ``span[0]``; the schedule runs up to ``span[1]``
        (``None``: all of it)."""
        cfg = self.config
        span = (0, cfg.iterations) if span is None else span
        padding = 0
        if compiled and self.device.type == "cpu":
            padding = _goal_padding(goals.shape[0], goals.shape[1], goals.element_size())
            goals = _repeat_last(goals, 1, goals.shape[1] + padding)
            warm = _repeat_warm(warm, 1, goals.shape[1])
        layout = self._layout if compiled else _layout
        origin, b_position, b_heading, obstacles, axes, goal_ahead, counts = layout(
            ego, goals, obstacles, mask, axes, cfg.start_acceleration, (cfg.ellipse_a, cfg.ellipse_b), cfg.a_max
        )
        if uniform == "find":
            count_values = counts.unique()
            uniform = int(count_values[0]) if count_values.numel() == 1 else None
        return _Prepared(
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
            warm=None if warm is None else _solver_layout(warm),
            first_iteration=span[0],
            last_iteration=span[1],
        )


def _layout(
    ego: torch.Tensor,
    goals: torch.Tensor,
    obstacles: torch.Tensor,
    mask: torch.Tensor,
    axes: Optional[torch.Tensor],
    start_acceleration: bool,
    semi_axes: tuple[float, float],
    a_max: float,
) -> tuple[Optional[torch.Tensor], ...]:
    """Inputs in the ego-relative frame and the solver layout (see :class:`_Prepared`).

    The start acceleration ``(a, v psidot)`` is held to the disc of radius ``a_max``: an ego
    braking harder than a plan may (the fallback's full brake) would otherwise make every
    candidate infeasible from its first sample, and the fallback would follow itself.

    Returns:
        origin (E, 2) [m]; b_position (n_eq, 2 E G); b_heading (4, E G); obstacles
        (M, N, 2, E, 1) in semi-axis units, absent slots parked; axes: ``None`` when every obstacle
        has ``semi_axes``, else the per-obstacle ``axes`` (E, M, 2) and their reciprocals as
        (M, 1, 4, E, 1) (a, b [m], 1/a, 1/b; absent slots given ``semi_axes``); goal_ahead (E, G) bool; counts (E,) int64 present obstacles per problem.
    """
    num_goals = goals.shape[1]
    origin = ego[:, EGO_X : EGO_Y + 1]  # (E, 2)
    psi0, v0 = ego[:, EGO_PSI], ego[:, EGO_V]
    a0, psidot0 = ego[:, EGO_A], ego[:, EGO_PSIDOT]
    cos0, sin0 = torch.cos(psi0), torch.sin(psi0)
    relative_goals = goals - origin[:, None, :]  # (E, G, 2)

    start_velocity = torch.stack([v0 * cos0, v0 * sin0])  # (2, E)
    rows = [torch.zeros_like(start_velocity), start_velocity]
    if start_acceleration:
        tangential, normal = a0, v0 * psidot0
        scale = (a_max * torch.rsqrt((tangential * tangential + normal * normal).clamp_min(_EPS_SQUARED))).clamp_max(1.0)
        tangential, normal = tangential * scale, normal * scale
        rows.append(torch.stack([tangential * cos0 - normal * sin0, tangential * sin0 + normal * cos0]))
    start = torch.stack(rows)[..., None].expand(-1, -1, -1, num_goals)  # (n_start, 2, E, G)
    end = relative_goals.permute(2, 0, 1).unsqueeze(0)  # (1, 2, E, G)
    b_position = torch.cat([start, end]).reshape(len(rows) + 1, -1)

    zeros = torch.zeros_like(psi0)
    b_heading = torch.stack([psi0, psidot0, zeros, zeros])[..., None].expand(-1, -1, num_goals)
    b_heading = b_heading.reshape(4, -1)

    relative = obstacles - origin[:, None, None, :]  # (E, M, N, 2)
    relative = torch.where(mask[:, :, None, None], relative, _PARKED_DISTANCE)
    if axes is None:
        scaled = relative.permute(1, 2, 3, 0).unsqueeze(-1) / relative.new_tensor(semi_axes).view(2, 1, 1)  # (M, N, 2, E, 1)
    else:
        axes = torch.where(mask[..., None], axes, axes.new_tensor(semi_axes))
        axes = axes.permute(1, 2, 0)[:, None, :, :, None]  # (M, 1, 2, E, 1)
        scaled = relative.permute(1, 2, 3, 0).unsqueeze(-1) / axes
        axes = torch.cat([axes, 1.0 / axes], dim=2).contiguous()  # reciprocals: products in the iterations
    return origin, b_position, b_heading, scaled.contiguous(), axes, relative_goals[..., 0] > 0, mask.sum(dim=1)


def _auto_compile(float32: bool, on_cpu: bool) -> tuple[bool, float]:
    """``compile="auto"`` -> (compiled, the default ``compile_after`` [s]): the compiled path where
    it is the fast one (float32, a kernel compiler found), each layout after
    :data:`AUTO_COMPILE_AFTER_S`, unless the environment variable ``MMPC_COMPILE`` says 0 (eager)
    or 1 (compiled at the first call)."""
    setting = os.environ.get(COMPILE_ENV, "").strip()
    if setting not in ("", "0", "1"):
        raise ValueError(f"environment variable {COMPILE_ENV} must be 0, 1 or unset; got {setting!r}")
    if setting:
        return setting == "1", 0.0
    return float32 and _kernel_compiler_found(on_cpu), AUTO_COMPILE_AFTER_S


def _kernel_compiler_found(on_cpu: bool) -> bool:
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


def _tiling(num_problems: int, num_goals: int, tile_size: Optional[int]) -> Optional[tuple[int, int]]:
    """(problems, goals) per tile for an E x G batch, or None when it fits one tile.

    Whole problems per tile when a problem's goals fit in one: as many as fit, or fewer where
    the batch fills its tiles less, rounded up to a power of two (so that batches of varying E,
    e.g. the cold and the warm rows of warm-started steps, share a few compiled layouts); else
    one problem per tile with its goals split evenly.
    """
    if tile_size is None or num_problems * num_goals <= tile_size:
        return None
    if num_goals <= tile_size:
        fit = tile_size // num_goals
        balanced = _ceil_div(num_problems, _ceil_div(num_problems, fit))
        return min(1 << (balanced - 1).bit_length(), fit), num_goals
    return 1, _ceil_div(num_goals, _ceil_div(num_goals, tile_size))


def _problem_bucket(num_problems: int, num_goals: int, tile_size: Optional[int]) -> int:
    """Problems to solve for an E x G batch that fits one tile: E rounded up to a power of two
    (at most a full tile), so that batches of varying E (rows that replan, episodes that end)
    share a few compiled layouts instead of compiling one each. Without tiles: E."""
    if tile_size is None:
        return num_problems
    return max(num_problems, min(1 << (num_problems - 1).bit_length(), tile_size // num_goals))


def _graph_bucket(num_problems: int) -> int:
    """Problems to solve on the compiled CUDA path: E rounded up to 1-8, 10, 12, 14, 16, 20, 24, 28,
    32, 40, ... (four sizes per octave, at most 25 % padding), so that batches of varying E share
    a few captured graphs."""
    if num_problems <= 8:
        return num_problems
    step = 1 << (num_problems.bit_length() - 3)
    return _ceil_div(num_problems, step) * step


class _GraphSolve:
    """One call layout's solve captured as a CUDA graph: static inputs copied in, replayed, the
    outputs cloned out."""

    def __init__(self, graph: "torch.cuda.CUDAGraph", inputs: tuple[Optional[torch.Tensor], ...], output: SolveResult) -> None:
        self.graph, self.inputs, self.output = graph, inputs, output

    @staticmethod
    def capture(solve, inputs: tuple[Optional[torch.Tensor], ...]) -> Optional["_GraphSolve"]:
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
        return _GraphSolve(graph, static, output)

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


def _ceil_div(numerator: int, denominator: int) -> int:
    return -(-numerator // denominator)


def _repeat_last(tensor: Optional[torch.Tensor], dim: int, size: int) -> Optional[torch.Tensor]:
    """``tensor`` grown along ``dim`` to ``size`` entries with copies of its last one (``None`` stays ``None``)."""
    if tensor is None:
        return None
    index = torch.arange(size, device=tensor.device).clamp_max(tensor.shape[dim] - 1)
    return tensor.index_select(dim, index)


def _take_rows(tensors: tuple[Optional[torch.Tensor], ...], rows: torch.Tensor) -> tuple[Optional[torch.Tensor], ...]:
    """The problems ``rows`` of each tensor (``None`` stays ``None``)."""
    return tuple(None if t is None else t[rows] for t in tensors)


def _repeat_warm(warm: Optional[WarmStart], dim: int, size: int) -> Optional[WarmStart]:
    """:func:`_repeat_last` of every field of a warm start (``None`` stays ``None``)."""
    return None if warm is None else WarmStart(*(_repeat_last(field, dim, size) for field in warm))


def _solver_layout(warm: WarmStart) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A batch-first warm start -> the iterations' (K, 2B), (K, 2B), (K, B), columns ordered (axis, e, g)."""
    order = warm.position.shape[-1]
    return (warm.position.permute(3, 2, 0, 1).reshape(order, -1), warm.multipliers.permute(3, 2, 0, 1).reshape(order, -1),
            warm.heading_multipliers.permute(2, 0, 1).reshape(order, -1))


def _validate_warm(warm: Optional[WarmStart], iterations: Optional[int], config: OptimizerConfig, batch: tuple[int, int],
                   dtype: torch.dtype, device: torch.device) -> tuple[Optional[WarmStart], int]:
    """A warm start checked against the (E, G) ``batch`` and cast to ``dtype``, and the first
    iteration it runs from (0 without one)."""
    if warm is None:
        if iterations is not None:
            raise ValueError(f"`warm_iterations` needs a `warm` start; got warm_iterations={iterations!r} without one")
        return None, 0
    if not isinstance(warm, WarmStart):
        raise TypeError(f"`warm` must be a mmpc.WarmStart (a result's `warm`); got {type(warm).__name__}")
    if isinstance(iterations, bool) or not isinstance(iterations, int) or not 1 <= iterations <= config.iterations:
        raise ValueError(f"`warm_iterations` must be an int in [1, {config.iterations}]; got {iterations!r}")
    order = config.order + 1
    expected = {"position": (*batch, 2, order), "multipliers": (*batch, 2, order), "heading_multipliers": (*batch, order)}
    fields = []
    for name, shape in expected.items():
        value = getattr(warm, name)
        if not isinstance(value, torch.Tensor) or tuple(value.shape) != shape:
            got = tuple(value.shape) if isinstance(value, torch.Tensor) else type(value).__name__
            raise ValueError(f"`warm.{name}` must have shape {shape} for this batch; got {got}")
        if value.device != device:
            raise ValueError(f"`warm.{name}` is on {value.device} but the optimizer is on {device}; move it with .to()")
        fields.append(value.to(dtype))  # problems with NaN or inf start cold (forward)
    return WarmStart(*fields), config.iterations - iterations


def _goal_padding(num_problems: int, num_goals: int, element_size: int) -> int:
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


class _Limits(NamedTuple):
    """Constants of the iterations, as Python floats: constants to a compiler (no memory reads)."""

    v_min: float  # m/s
    v_max: float  # m/s
    a_max: float  # m/s^2, radius of the disc the acceleration step projects onto (a_max less the back-off)
    heading: Optional[float]  # rad, the band the heading targets are clipped to; None: unclipped
    ellipse_a: float  # m, obstacle ellipse semi-axis along x
    ellipse_b: float  # m, along y
    obstacle_radius: float  # normalised radius the obstacle step projects onto (1 + back-off)
    polynomial_trig: bool = False  # sin, cos, atan2 from mmpc.trig (compiled CPU float32) or torch


def _atan2(y: torch.Tensor, x: torch.Tensor, limits: _Limits) -> torch.Tensor:
    """Elementwise angle of (x, y) [rad], from the implementation ``limits`` selects."""
    return trig.atan2(y, x) if limits.polynomial_trig else torch.atan2(y, x)


def _safe_sqrt(square: torch.Tensor) -> torch.Tensor:
    """``square.sqrt()`` with gradient 0 (a norm's subgradient) instead of NaN where ``square`` is 0."""
    zero = square == 0
    return torch.where(zero, 0.0, torch.where(zero, 1.0, square).sqrt())


class _State(NamedTuple):
    """What one iteration hands to the next. Columns ordered (axis, e, g)."""

    c: torch.Tensor  # (K, 2B) x, y coefficients relative to the start
    scaled_residual: torch.Tensor  # (K, 2B) rho_k F^T (F c - g)
    multipliers: torch.Tensor  # (K, 2B)
    multipliers_psi: torch.Tensor  # (K, B)


class _Step(NamedTuple):
    """Last iterate of a run of iterations, for the outputs."""

    c_psi: torch.Tensor  # (K, B)
    samples: torch.Tensor  # (3N, 2, E, G)
    residuals: _Residuals
    records: list  # per-iteration (E, G, 3) residual norms when requested


def _iterate(
    state: _State,
    b_position: torch.Tensor,
    b_heading: torch.Tensor,
    obstacles: torch.Tensor,
    axes: Optional[torch.Tensor],
    position: torch.Tensor,
    gather: torch.Tensor,
    heading: torch.Tensor,
    heading_gather: torch.Tensor,
    samples_operator: torch.Tensor,
    heading_basis: torch.Tensor,
    limits: _Limits,
    history: bool,
) -> tuple[_State, _Step]:
    """Run U = ``gather.shape[0]`` iterations; every operator argument is sliced to those U.

    Shapes: ``position`` (U, 2, K, D) when every problem has the same obstacle count, else
    (U, E, 2, K, D); ``gather`` (U, K, 3N); ``heading`` (U, K, N + K + 4); ``heading_gather``
    (U, K, N); see :class:`mmpc.operators.Operators`; ``obstacles`` and ``axes`` as
    :class:`_Prepared`. Pure tensor code without host
    synchronisation, so that it can be compiled.
    """
    c, scaled_residual, multipliers, multipliers_psi = state
    n = samples_operator.shape[0] // 3
    num_problems, num_goals = obstacles.shape[3], b_heading.shape[1] // obstacles.shape[3]
    records = []
    for u in range(gather.shape[0]):
        stacked = torch.cat([c, scaled_residual, multipliers, b_position])
        c = _position_qp(position[u], stacked, num_problems)
        samples = (samples_operator @ c).view(3 * n, 2, num_problems, num_goals)
        psi_target = _atan2(samples[2 * n :, 1], samples[2 * n :, 0], limits).view(n, -1)  # (N, B)
        if limits.heading is not None:
            psi_target = psi_target.clamp(-limits.heading, limits.heading)
        heading_rhs = torch.cat([psi_target, multipliers_psi, b_heading])
        c_psi = heading[u] @ heading_rhs
        psi = heading_basis @ c_psi
        # The targets read back from the right-hand side: a compiler would otherwise recompute atan2.
        multipliers_psi = torch.addmm(multipliers_psi, heading_gather[u], heading_rhs[:n] - psi)
        residuals = _closed_form_steps(samples, psi.view(n, num_problems, num_goals), obstacles, axes, limits)
        scaled_residual = gather[u] @ residuals.stacked.view(3 * n, -1)
        multipliers = multipliers - scaled_residual
        if history:
            records.append(_residual_norms(residuals, _obstacle_offsets(samples[:n], obstacles, axes, limits), axes, limits))
    return _State(c, scaled_residual, multipliers, multipliers_psi), _Step(c_psi, samples, residuals, records)


def _position_qp(operator: torch.Tensor, stacked: torch.Tensor, num_problems: int) -> torch.Tensor:
    """x, y QP: ``stacked`` (D, 2B) -> (K, 2B); ``operator`` (2, K, D), one per axis, shared by
    every problem, or (E, 2, K, D) per problem."""
    rows = stacked.shape[0]
    if operator.ndim == 3:
        solved = operator @ stacked.view(rows, 2, -1).transpose(0, 1)  # (2, K, B)
        return solved.transpose(0, 1).reshape(operator.shape[1], -1)
    per_problem = stacked.view(rows, 2, num_problems, -1).permute(2, 1, 0, 3)  # (E, 2, D, G)
    solved = operator @ per_problem  # (E, 2, K, G)
    return solved.permute(2, 1, 0, 3).reshape(operator.shape[2], -1)


def _closed_form_steps(
    samples: torch.Tensor, psi: torch.Tensor, obstacles: torch.Tensor, axes: Optional[torch.Tensor], limits: _Limits
) -> _Residuals:
    """Closed-form speed, obstacle and acceleration steps and the residual F c - g.

    Args:
        samples: (3N, 2, E, G) [position; acceleration; velocity] relative to the start.
        psi: (N, E, G) heading [rad].
        obstacles: (M, N, 2, E, 1) obstacle centres in semi-axis units.
        axes: (M, 1, 4, E, 1) per-obstacle semi-axes and reciprocals (:class:`_Prepared`); ``None``: ``limits``'.
        limits: speed and acceleration bounds, ellipse semi-axes.
    """
    n = psi.shape[0]
    position, acceleration, velocity = samples[:n], samples[n : 2 * n], samples[2 * n :]
    sin, cos = trig.sincos(psi) if limits.polynomial_trig else (torch.sin(psi), torch.cos(psi))
    heading = torch.stack([cos, sin], dim=1)  # (N, 2, E, G)
    speed = (velocity * heading).sum(dim=1).clamp(limits.v_min, limits.v_max)
    velocity_residual = torch.addcmul(velocity, speed.unsqueeze(1), heading, value=-1.0)

    norm_squared = (acceleration * acceleration).sum(dim=1, keepdim=True)
    inverse_norm = norm_squared.clamp_min(_EPS_SQUARED).rsqrt()
    excess = torch.rsub(inverse_norm, 1.0, alpha=limits.a_max).clamp_min(0.0)
    acceleration_residual = acceleration * excess

    offset_x, offset_y, outward = _obstacle_offsets(position, obstacles, axes, limits)
    if axes is None:
        push = torch.stack([(offset_x * outward).sum(dim=0) * limits.ellipse_a,
                            (offset_y * outward).sum(dim=0) * limits.ellipse_b], dim=1)
    else:
        push = torch.stack([(offset_x * outward * axes[:, :, 0]).sum(dim=0),
                            (offset_y * outward * axes[:, :, 1]).sum(dim=0)], dim=1)
    return _Residuals(stacked=torch.cat([push, acceleration_residual, velocity_residual]), speed=speed)


def _obstacle_offsets(
    position: torch.Tensor, obstacles: torch.Tensor, axes: Optional[torch.Tensor], limits: _Limits
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Every point relative to every ellipse, in semi-axis units: ``(dx, dy, (R/r - 1)_+)``.

    ``r = sqrt(dx^2 + dy^2)`` is the normalised distance; the projection of a point with
    r < R onto the ellipse scaled by R (``limits.obstacle_radius``: 1, or 1 + the back-off)
    moves it by ``(dx, dy) (R/r - 1)`` (times the semi-axes in metres), a point outside is
    left where it is.

    Args:
        position: (N, 2, E, G) sample positions relative to the start [m].
        obstacles: (M, N, 2, E, 1) obstacle centres in semi-axis units.
        axes: (M, 1, 4, E, 1) per-obstacle semi-axes and reciprocals (:class:`_Prepared`); ``None``: every
            obstacle has ``limits``'.
        limits: holds the ellipse semi-axes (a, b) [m] and R.

    Returns:
        dx, dy, outward, each (M, N, E, G). Inside a compiled chunk these are never stored:
        the sums over M fuse into one pass over the positions.
    """
    # x and y as separate contiguous planes: far fewer memory passes than an axis dimension.
    # Products with the reciprocals: a vector division costs several multiplications.
    if axes is None:
        offset_x = position[:, 0] * (1.0 / limits.ellipse_a) - obstacles[:, :, 0]
        offset_y = position[:, 1] * (1.0 / limits.ellipse_b) - obstacles[:, :, 1]
    else:  # (N, E, G) x (M, 1, E, 1)
        offset_x = position[:, 0] * axes[:, :, 2] - obstacles[:, :, 0]
        offset_y = position[:, 1] * axes[:, :, 3] - obstacles[:, :, 1]
    distance_squared = offset_x * offset_x + offset_y * offset_y
    inverse_distance = distance_squared.clamp_min(_EPS_SQUARED).rsqrt()
    if limits.obstacle_radius != 1.0:  # a Python constant: no branch in the compiled kernels
        inverse_distance = inverse_distance * limits.obstacle_radius
    outward = inverse_distance.sub(1.0).clamp_min(0.0)
    return offset_x, offset_y, outward


def _residual_norms(
    residuals: _Residuals, offsets: tuple[torch.Tensor, torch.Tensor, torch.Tensor], axes: Optional[torch.Tensor],
    limits: _Limits,
) -> torch.Tensor:
    """(E, G, 3) L2 norms of the obstacle [m], acceleration [m/s^2] and non-holonomic [m/s] residuals:
    distances to the sets the iterations project onto (backed off where the config says so).

    The obstacle norm is over every (obstacle, sample) gap, hence the per-obstacle ``offsets``
    of :func:`_obstacle_offsets` rather than the push summed over obstacles.
    """
    n = residuals.speed.shape[0]
    offset_x, offset_y, outward = offsets
    if axes is None:
        gap_x = offset_x * outward * limits.ellipse_a
        gap_y = offset_y * outward * limits.ellipse_b
    else:
        gap_x = offset_x * outward * axes[:, :, 0]
        gap_y = offset_y * outward * axes[:, :, 1]
    stacked = residuals.stacked
    norms = torch.stack(
        [
            (gap_x * gap_x + gap_y * gap_y).sum(dim=(0, 1)),
            (stacked[n : 2 * n] ** 2).sum(dim=(0, 1)),
            (stacked[2 * n :] ** 2).sum(dim=(0, 1)),
        ],
        dim=-1,
    )
    return _safe_sqrt(norms)


def _start(
    b_position: torch.Tensor,
    obstacles: torch.Tensor,
    axes: Optional[torch.Tensor],
    position_init: torch.Tensor,
    samples_operator: torch.Tensor,
    gather: torch.Tensor,
    limits: _Limits,
) -> _State:
    """Cold start: the smoothest trajectories meeting the boundary conditions, zero multipliers.

    Its residual (heading taken along the velocity) is mapped with ``gather`` = ``gather[0]``,
    ready for the first position QP. Shapes as in :func:`_iterate`.
    """
    c = _position_qp(position_init, b_position, obstacles.shape[3])  # (K, 2B)
    return _State(
        c=c,
        scaled_residual=_scaled_residual(c, obstacles, axes, samples_operator, gather, limits),
        multipliers=torch.zeros_like(c),
        multipliers_psi=c.new_zeros(c.shape[0], c.shape[1] // 2),
    )


def _resume(
    c: torch.Tensor, multipliers: torch.Tensor, multipliers_psi: torch.Tensor, obstacles: torch.Tensor,
    axes: Optional[torch.Tensor], samples_operator: torch.Tensor, gather: torch.Tensor, limits: _Limits,
) -> _State:
    """The iterations' state from a warm start's iterates (K, 2B), (K, 2B), (K, B): the residual
    scaled as the first iteration run expects (``gather``: the rho of the iteration before it)."""
    return _State(c, _scaled_residual(c, obstacles, axes, samples_operator, gather, limits), multipliers, multipliers_psi)


def _scaled_residual(
    c: torch.Tensor, obstacles: torch.Tensor, axes: Optional[torch.Tensor], samples_operator: torch.Tensor,
    gather: torch.Tensor, limits: _Limits,
) -> torch.Tensor:
    """(K, 2B) ``gather @ (F c - g)`` of coefficients ``c`` (K, 2B), the heading taken along the
    velocity: what the position QP after ``gather``'s iteration reads. Shapes as in :func:`_iterate`."""
    n = samples_operator.shape[0] // 3
    samples = (samples_operator @ c).view(3 * n, 2, obstacles.shape[3], -1)
    psi = _atan2(samples[2 * n :, 1], samples[2 * n :, 0], limits)
    residuals = _closed_form_steps(samples, psi, obstacles, axes, limits)
    return gather @ residuals.stacked.view(3 * n, -1)


def _summarise(
    c: torch.Tensor,
    step: _Step,
    obstacles: torch.Tensor,
    axes: Optional[torch.Tensor],
    mask: torch.Tensor,
    origin: torch.Tensor,
    goal_ahead: torch.Tensor,
    num_goals: int,
    heading_basis: torch.Tensor,
    heading_rate_basis: torch.Tensor,
    config: OptimizerConfig,
    limits: _Limits,
) -> tuple[list[torch.Tensor], torch.Tensor, torch.Tensor, list[torch.Tensor], torch.Tensor]:
    """Trajectories, checks and status of the last iterate, batch first.

    Args:
        c: (K, 2 E G') final x, y coefficients, G' >= G goals (padding goals come last).
        step: the last iterate (heading coefficients, samples, residuals) with G' goals.
        obstacles: (M, N, 2, E, 1) in semi-axis units; axes: as :class:`_Prepared`; mask: (E, M); origin: (E, 2) [m];
        goal_ahead: (E, G').
        num_goals: G, the goals kept (the first G).

    Returns:
        fields: the nine (E, G, N) :class:`mmpc.Trajectories` fields after ``times``;
        coefficients (E, G, 3, K); norms (E, G, 3); scalars (min obstacle distance, max heading
        deviation, max acceleration, max non-holonomic error), each (E, G); status (E, G) int32.
    """
    n = config.num_steps
    k = c.shape[0]
    num_problems, padded_goals = step.samples.shape[2], step.samples.shape[3]
    goals = slice(0, num_goals)

    def batch_first(t: torch.Tensor) -> torch.Tensor:  # (N, E, G') -> (E, G, N)
        return t[..., goals].permute(1, 2, 0).contiguous()

    samples = step.samples[..., goals]
    position, acceleration, velocity = samples[:n], samples[n : 2 * n], samples[2 * n :]
    residuals = _Residuals(step.residuals.stacked[..., goals], step.residuals.speed[..., goals])
    psi = (heading_basis @ step.c_psi).view(n, num_problems, padded_goals)
    psidot = (heading_rate_basis @ step.c_psi).view(n, num_problems, padded_goals)

    offsets = _obstacle_offsets(position, obstacles, axes, limits)  # each (M, N, E, G)
    norms = _residual_norms(residuals, offsets, axes, limits)
    distance_squared = offsets[0] ** 2 + offsets[1] ** 2
    present = mask.T[:, None, :, None]
    inf = torch.full((), float("inf"), dtype=c.dtype, device=c.device)
    distance_squared = torch.where(present, distance_squared, inf)
    # An always-absent extra slot keeps the minimum defined (+inf) when M = 0.
    distance_squared = torch.cat([distance_squared, inf.expand(1, *distance_squared.shape[1:])])
    min_distance = _safe_sqrt(distance_squared.amin(dim=(0, 1)))
    start_distance = distance_squared[:, 0].amin(dim=0)

    acceleration_norm = _safe_sqrt((acceleration * acceleration).sum(dim=1))  # (N, E, G)
    velocity_residual = residuals.stacked[2 * n :]
    nonholonomic_error = _safe_sqrt((velocity_residual * velocity_residual).sum(dim=1))
    path_speed = (velocity * velocity).sum(dim=1).sqrt()  # status only: no gradient
    heading_deviation = psi[..., goals].abs().amax(dim=0)
    max_acceleration = acceleration_norm.amax(dim=0)
    max_nonholonomic = nonholonomic_error.amax(dim=0)

    max_heading = math.radians(config.max_heading_deg)
    bits = [
        (min_distance < 1.0 - config.obstacle_tolerance, Status.OBSTACLE),
        (max_acceleration > config.a_max + config.acceleration_tolerance, Status.ACCELERATION),
        (max_nonholonomic > config.nonholonomic_tolerance, Status.NONHOLONOMIC),
        (heading_deviation > max_heading, Status.HEADING),
        (
            (path_speed.amax(dim=0) > config.v_max + config.speed_tolerance)
            | (path_speed.amin(dim=0) < config.v_min - config.speed_tolerance),
            Status.SPEED,
        ),
        (start_distance < (1.0 - config.obstacle_tolerance) ** 2, Status.START_IN_COLLISION),
        (~goal_ahead[:, goals], Status.GOAL_BEHIND),
    ]
    status = torch.zeros(num_problems, num_goals, dtype=torch.int32, device=c.device)
    for condition, flag in bits:
        status = status | condition.to(torch.int32) * int(flag)

    start = origin[:, None, None, :]  # (E, 1, 1, 2)
    fields = [
        batch_first(position[:, 0]) + start[..., 0],
        batch_first(position[:, 1]) + start[..., 1],
        batch_first(psi),
        batch_first(residuals.speed),
        batch_first(velocity[:, 0]),
        batch_first(velocity[:, 1]),
        batch_first(acceleration[:, 0]),
        batch_first(acceleration[:, 1]),
        batch_first(psidot),
    ]
    coefficients = torch.cat(
        [c.view(k, 2, num_problems, padded_goals), step.c_psi.view(k, 1, num_problems, padded_goals)], dim=1
    )[..., goals].permute(2, 3, 1, 0)
    finite = torch.stack([f.isfinite().all(dim=-1) for f in fields]).all(dim=0)
    finite = finite & coefficients.isfinite().flatten(2).all(dim=-1)
    status = status | (~finite).to(torch.int32) * int(Status.NUMERICAL)
    fields, coefficients, norms, scalars = _replace_nonfinite(
        finite, origin, fields, coefficients, norms, [min_distance, heading_deviation, max_acceleration, max_nonholonomic]
    )
    return fields, coefficients, norms, scalars, status


def _replace_nonfinite(
    finite: torch.Tensor,
    origin: torch.Tensor,  # (E, 2)
    fields: list[torch.Tensor],
    coefficients: torch.Tensor,
    norms: torch.Tensor,
    scalars: list[torch.Tensor],
) -> tuple[list[torch.Tensor], torch.Tensor, torch.Tensor, list[torch.Tensor]]:
    """Put a standing-still placeholder where an element went non-finite (it is flagged NUMERICAL)."""
    bad = ~finite[..., None]
    zero = torch.zeros((), dtype=coefficients.dtype, device=coefficients.device)
    inf = torch.full((), float("inf"), dtype=coefficients.dtype, device=coefficients.device)
    start = torch.nan_to_num(origin, nan=0.0, posinf=0.0, neginf=0.0)[:, None, None, :]
    placeholders = [start[..., 0], start[..., 1]] + [zero] * (len(fields) - 2)
    fields = [torch.where(bad, placeholder, field) for field, placeholder in zip(fields, placeholders)]
    coefficients = torch.where(bad[..., None], zero, coefficients)
    norms = torch.where(bad, inf, norms)
    bad = bad[..., 0]
    scalars = [torch.where(bad, inf, s) for s in scalars]
    scalars[0] = torch.where(bad, zero, scalars[0])  # no claimed clearance
    return fields, coefficients, norms, scalars


def _check_tensor(name: str, value: object, ndim: int, shape_doc: str) -> torch.Tensor:
    if not isinstance(value, torch.Tensor):
        raise TypeError(f"`{name}` must be a torch.Tensor of shape {shape_doc}; got {type(value).__name__}")
    if value.ndim != ndim:
        raise ValueError(f"`{name}` must have shape {shape_doc}; got {tuple(value.shape)}")
    return value


def _validate(
    problem: ProblemBatch, config: OptimizerConfig, dtype: torch.dtype, device: torch.device
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, Optional[torch.Tensor]]:
    """Check shapes, dtypes, devices and values; return (ego, goals, obstacles, mask, axes) cast to ``dtype``."""
    if not isinstance(problem, ProblemBatch):
        raise TypeError(f"`problem` must be a mmpc.ProblemBatch; got {type(problem).__name__}")
    n = config.num_steps
    ego = _check_tensor("ego", problem.ego, 2, f"(E, {len(EGO_FIELDS)})")
    goals = _check_tensor("goals", problem.goals, 3, "(E, G, 2)")
    obstacles = _check_tensor("obstacles", problem.obstacles, 4, f"(E, M, {n}, 2)")
    num_problems = ego.shape[0]
    if ego.shape[1] != len(EGO_FIELDS):
        raise ValueError(
            f"`ego` must have shape (E, {len(EGO_FIELDS)}) with fields {EGO_FIELDS}; got {tuple(ego.shape)}"
        )
    if num_problems == 0:
        raise ValueError(f"empty batch: `ego` must hold at least one problem; got shape {tuple(ego.shape)}")
    if goals.shape[0] != num_problems or goals.shape[2] != 2:
        raise ValueError(f"`goals` must have shape ({num_problems}, G, 2); got {tuple(goals.shape)}")
    if goals.shape[1] == 0:
        raise ValueError(f"empty batch: `goals` must hold at least one goal; got shape {tuple(goals.shape)}")
    if obstacles.shape[0] != num_problems or obstacles.shape[2] != n or obstacles.shape[3] != 2:
        raise ValueError(
            f"`obstacles` must have shape ({num_problems}, M, {n}, 2); got {tuple(obstacles.shape)}"
        )
    num_slots = obstacles.shape[1]
    if num_slots > config.max_obstacles:
        raise ValueError(
            f"`obstacles` has {num_slots} slots but the optimizer was built for at most "
            f"max_obstacles={config.max_obstacles}"
        )
    mask = problem.obstacle_mask
    if mask is None:
        mask = torch.ones(num_problems, num_slots, dtype=torch.bool, device=obstacles.device)
    mask = _check_tensor("obstacle_mask", mask, 2, f"({num_problems}, {num_slots})")
    if mask.dtype != torch.bool:
        raise TypeError(f"`obstacle_mask` must be a bool tensor; got dtype {mask.dtype}")
    if tuple(mask.shape) != (num_problems, num_slots):
        raise ValueError(f"`obstacle_mask` must have shape ({num_problems}, {num_slots}); got {tuple(mask.shape)}")
    axes = problem.obstacle_axes
    if axes is not None:
        axes = _check_tensor("obstacle_axes", axes, 3, f"({num_problems}, {num_slots}, 2)")
        if tuple(axes.shape) != (num_problems, num_slots, 2):
            raise ValueError(f"`obstacle_axes` must have shape ({num_problems}, {num_slots}, 2); got {tuple(axes.shape)}")
    floats = (("ego", ego), ("goals", goals), ("obstacles", obstacles)) + ((("obstacle_axes", axes),) if axes is not None else ())
    for name, tensor in floats:
        if not tensor.dtype.is_floating_point:
            raise TypeError(f"`{name}` must be a floating tensor; got dtype {tensor.dtype}")
    for name, tensor in floats + (("obstacle_mask", mask),):
        if tensor.device != device:
            raise ValueError(f"`{name}` is on {tensor.device} but the optimizer is on {device}; move it with .to()")
    if axes is not None:
        axes = axes.to(dtype)
        bad_axes = mask & ~((axes > 0) & axes.isfinite()).all(dim=2)
        if bool(bad_axes.any()):
            raise ValueError(f"`obstacle_axes` must be finite and > 0 m for present obstacles; got "
                             f"{axes[bad_axes][:4].tolist()} at (problem, slot) {bad_axes.nonzero()[:4].tolist()}")

    ego, goals, obstacles = (t.to(dtype) for t in (ego, goals, obstacles))
    ego_finite = ego.isfinite().all(dim=1)
    goals_finite = goals.isfinite().all(dim=2)
    obstacles_finite = obstacles.isfinite().all(dim=3).all(dim=2) | ~mask
    negative_speed = ego[:, EGO_V] < 0
    checks = torch.stack(
        [~ego_finite.all(), ~goals_finite.all(), ~obstacles_finite.all(), negative_speed.any()]
    ).tolist()
    if checks[0]:
        rows = (~ego_finite).nonzero().flatten().tolist()
        raise ValueError(f"`ego` contains NaN or inf in problem(s) {rows}")
    if checks[1]:
        rows = (~goals_finite).nonzero().tolist()
        raise ValueError(f"`goals` contains NaN or inf at (problem, goal) {rows}")
    if checks[2]:
        rows = (~obstacles_finite).nonzero().tolist()
        raise ValueError(
            f"`obstacles` contains NaN or inf at present (problem, slot) {rows}; "
            "mark absent slots False in `obstacle_mask`"
        )
    if checks[3]:
        rows = negative_speed.nonzero().flatten().tolist()
        speeds = ego[negative_speed, EGO_V].tolist()
        raise ValueError(f"ego speed `v` must be >= 0 m/s; got {speeds} in problem(s) {rows}")
    return ego, goals, obstacles, mask, axes
