"""The trajectory NLP of the CasADi/IPOPT baselines (standard MPC and batch of goal NLPs).

Direct multiple shooting of the kinematic model the batch optimizer plans with, on the same
horizon ``t_f``, with the same bounds and obstacle ellipses. State and control::

    s = (x, y, psi, v, a, omega)   [m, m, rad, m/s, m/s^2, rad/s]
    u = (j, omega_dot)             [m/s^3, rad/s^2]

    x' = v cos psi,  y' = v sin psi,  psi' = omega,  v' = a,  a' = j,  omega' = omega_dot

on K intervals of ``dt = t_f / K`` (one RK4 step each; ``s_{k+1} = RK4(s_k, u_k)`` is an
equality constraint). The acceleration of the path is ``(xddot, yddot) = a (cos, sin) +
v omega (-sin, cos)``, so ``|(xddot, yddot)|^2 = a^2 + v^2 omega^2``. Constraints, at every knot
k >= 1 (knot 0 is the measured state):

* ``v_min <= v_k <= v_max``, ``|psi_k| <= max_heading``, ``y`` inside the road minus
  ``road_margin`` (each band widened to include the start value, as the MPC's road filter does);
* ``a_k^2 + v_k^2 omega_k^2 <= a_max^2``;
* ``((x_k - o_jx(t_k)) / a)^2 + ((y_k - o_jy(t_k)) / b)^2 >= 1`` for every obstacle slot j
  (absent slots parked far away), with ``o_j`` the MPC's prediction (:meth:`mmpc.MPC.predict`);
* end heading and heading rate 0 (the optimizer's boundary conditions).

Objective: smoothness ``sum_k dt [w_xy (a_k^2 + v_k^2 omega_k^2) + w_psi omega_dot_k^2 +
w_j j_k^2]`` (the weights of :class:`mmpc.OptimizerConfig` on ``xddot, yddot`` and ``psiddot``,
plus a small jerk weight), and either

* ``goal`` mode: the end position equals the goal (the batch optimizer's problem, one goal), or
* ``meta`` mode: ``+ sum_k dt * stage(v_k, y_k)`` with ``stage`` the scenario's meta-cost term
  (:meth:`mmpc.scenario.CruiseObjective.stage_cost`); no goal (the standard MPC).

CasADi is an optional dependency (``pip install mmpc[baselines]``); it is imported on use.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any, Callable, NamedTuple, Optional

import numpy as np
import torch

from mmpc.config import require_int, require_non_negative, require_positive
from mmpc.result import Trajectories
from mmpc.road import Road
from mmpc.solver.config import OptimizerConfig

#: Layout of the NLP state.
STATE_FIELDS = ("x", "y", "psi", "v", "a", "omega")
NUM_STATES, NUM_CONTROLS = 6, 2
#: Where absent obstacle slots are parked, relative to the ego [m].
_PARKED = 1.0e4
#: Return statuses of IPOPT that count as solved.
SOLVED_STATUSES = ("Solve_Succeeded", "Solved_To_Acceptable_Level")


def require_casadi() -> Any:
    """Import CasADi or raise an ImportError that says how to install it."""
    try:
        import casadi
    except ImportError as error:  # pragma: no cover - depends on the environment
        raise ImportError(
            "the CasADi/IPOPT baselines (standard-mpc, batch-nlp) need CasADi: pip install mmpc[baselines]"
        ) from error
    return casadi


@dataclass(frozen=True)
class NLPConfig:
    """Transcription and IPOPT settings of the baseline NLPs.

    Attributes:
        intervals: K shooting intervals over the horizon (dt = t_f / K) [-].
        jerk_weight: weight of ``j^2`` in the objective (regularises the third derivative) [-].
        max_iter: IPOPT iteration limit [-].
        tol: IPOPT's convergence tolerance [-].
        feasibility_tolerance: a solution counts as feasible when no constraint (dynamics
            included, in the constraint's own units) is violated by more than this, whatever
            IPOPT's return status [-].
        max_cpu_time: IPOPT's CPU-time limit per solve [s].
    """

    intervals: int = 40
    jerk_weight: float = 0.1
    max_iter: int = 100
    tol: float = 1e-6
    feasibility_tolerance: float = 1e-3
    max_cpu_time: float = 5.0

    def __post_init__(self) -> None:
        require_int("", low=2, intervals=self.intervals)
        require_int("", low=1, max_iter=self.max_iter)
        require_positive("", tol=self.tol, feasibility_tolerance=self.feasibility_tolerance, max_cpu_time=self.max_cpu_time)
        require_non_negative("", jerk_weight=self.jerk_weight)


class NLPSolution(NamedTuple):
    """One IPOPT solve.

    Fields:
        states: (K + 1, 6) knot states as :data:`STATE_FIELDS`.
        controls: (K, 2) jerk [m/s^3] and heading acceleration [rad/s^2] per interval.
        status: IPOPT's return status (e.g. ``"Solve_Succeeded"``).
        iterations: IPOPT iterations.
        violation: largest constraint violation of the returned point (recomputed) [-].
        feasible: ``violation <= feasibility_tolerance`` and the values are finite.
        objective: the objective at the returned point.
        solve_ms: wall time of the IPOPT call [ms].
        primal: the full decision vector (for warm starts).
        multipliers_g: constraint multipliers (for warm starts).
    """

    states: np.ndarray
    controls: np.ndarray
    status: str
    iterations: int
    violation: float
    feasible: bool
    objective: float
    solve_ms: float
    primal: np.ndarray
    multipliers_g: np.ndarray


class TrajectoryNLP:
    """One CasADi/IPOPT NLP, built once and solved for many (state, obstacles, goal) values.

    Args:
        optimizer: horizon, bounds, ellipse and smoothness weights (the batch optimizer's).
        road: the road (its edges bound ``y``).
        road_margin: distance kept from the road edges [m].
        num_obstacles: M obstacle slots.
        config: transcription and IPOPT settings.
        stage_cost: ``stage(v, y) -> cost`` written in plain arithmetic (it is called with
            CasADi symbols), for ``meta`` mode; ``None`` builds the ``goal`` mode NLP.

    Shapes (in :meth:`solve`):
        ego: (6,) as :data:`mmpc.EGO_FIELDS`.
        obstacles: (M, K + 1, 2) predicted centres at :attr:`times` [m].
        mask: (M,) bool, present slots.
        goal: (2,) end position [m] (``goal`` mode).
    """

    def __init__(
        self,
        optimizer: OptimizerConfig,
        road: Road,
        road_margin: float,
        num_obstacles: int,
        config: Optional[NLPConfig] = None,
        stage_cost: Optional[Callable[[Any, Any], Any]] = None,
    ) -> None:
        ca = require_casadi()
        self.optimizer = optimizer
        self.road = road
        self.road_margin = float(road_margin)
        self.num_obstacles = int(num_obstacles)
        self.config = config if config is not None else NLPConfig()
        self.mode = "goal" if stage_cost is None else "meta"
        k_count = self.config.intervals
        self.dt = optimizer.horizon / k_count
        self.times = np.linspace(0.0, optimizer.horizon, k_count + 1)

        s = ca.SX.sym("s", NUM_STATES)
        u = ca.SX.sym("u", NUM_CONTROLS)
        rhs = ca.vertcat(s[3] * ca.cos(s[2]), s[3] * ca.sin(s[2]), s[5], s[4], u[0], u[1])
        f = ca.Function("f", [s, u], [rhs])
        k1 = f(s, u)
        k2 = f(s + 0.5 * self.dt * k1, u)
        k3 = f(s + 0.5 * self.dt * k2, u)
        k4 = f(s + self.dt * k3, u)
        step = ca.Function("rk4", [s, u], [s + self.dt / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)])

        states = ca.SX.sym("S", NUM_STATES, k_count + 1)
        controls = ca.SX.sym("U", NUM_CONTROLS, k_count)
        m = self.num_obstacles
        # Parameters: goal (2), obstacle x (M x K+1), obstacle y (M x K+1).
        goal = ca.SX.sym("goal", 2)
        obstacle_x = ca.SX.sym("ox", m, k_count + 1)
        obstacle_y = ca.SX.sym("oy", m, k_count + 1)
        params = ca.vertcat(goal, ca.vec(obstacle_x), ca.vec(obstacle_y))

        x, y, psi, v, a, omega = (states[i, :] for i in range(NUM_STATES))
        smooth = optimizer.weight_xy * (a[1:] ** 2 + (v[1:] * omega[1:]) ** 2)
        objective = self.dt * (ca.sum2(smooth) + optimizer.weight_psi * ca.sumsqr(controls[1, :])
                               + self.config.jerk_weight * ca.sumsqr(controls[0, :]))
        if stage_cost is not None:
            objective = objective + self.dt * sum(stage_cost(v[k], y[k]) for k in range(1, k_count + 1))

        rollout = step.map(k_count)(states[:, :-1], controls)
        groups = [("dynamics", ca.vec(states[:, 1:] - rollout), 0.0, 0.0)]
        groups.append(("acceleration", ca.vec(a[1:] ** 2 + (v[1:] * omega[1:]) ** 2), -ca.inf, optimizer.a_max**2))
        if m:
            ellipse = ((ca.repmat(x[1:], m, 1) - obstacle_x[:, 1:]) / optimizer.ellipse_a) ** 2 + (
                (ca.repmat(y[1:], m, 1) - obstacle_y[:, 1:]) / optimizer.ellipse_b
            ) ** 2
            groups.append(("obstacle", ca.vec(ellipse), 1.0, ca.inf))
        groups.append(("end_heading", ca.vertcat(psi[-1], omega[-1]), 0.0, 0.0))
        if stage_cost is None:
            groups.append(("goal", ca.vertcat(x[-1] - goal[0], y[-1] - goal[1]), 0.0, 0.0))
        constraints = ca.vertcat(*(g for _, g, _, _ in groups))
        self._lbg = np.concatenate([np.full(g.shape[0], low) for _, g, low, _ in groups])
        self._ubg = np.concatenate([np.full(g.shape[0], high) for _, g, _, high in groups])
        self.constraint_groups = {}
        first = 0
        for name, g, _, _ in groups:
            self.constraint_groups[name] = slice(first, first + g.shape[0])
            first += g.shape[0]

        decision = ca.vertcat(ca.vec(states), ca.vec(controls))
        self.num_variables = decision.shape[0]
        nlp = {"x": decision, "f": objective, "g": constraints, "p": params}
        options = {
            "print_time": False,
            "ipopt.print_level": 0,
            "ipopt.sb": "yes",
            "ipopt.max_iter": self.config.max_iter,
            "ipopt.tol": self.config.tol,
            "ipopt.max_cpu_time": self.config.max_cpu_time,
        }
        self._solver = ca.nlpsol("trajectory_nlp", "ipopt", nlp, options)
        self._constraints = ca.Function("g", [decision, params], [constraints])
        self._objective = ca.Function("f", [decision, params], [objective])

    # ----------------------------------------------------------------------------- inputs

    def parameters(self, obstacles: np.ndarray, mask: np.ndarray, goal: Optional[np.ndarray]) -> np.ndarray:
        """Parameter vector of one solve; absent obstacle slots are parked far away."""
        m, knots = self.num_obstacles, self.config.intervals + 1
        obstacles = np.asarray(obstacles, dtype=float)
        mask = np.asarray(mask, dtype=bool)
        if obstacles.shape != (m, knots, 2):
            raise ValueError(f"`obstacles` must have shape ({m}, {knots}, 2); got {obstacles.shape}")
        if mask.shape != (m,):
            raise ValueError(f"`mask` must have shape ({m},); got {mask.shape}")
        obstacles = np.where(mask[:, None, None], obstacles, _PARKED)
        if not np.isfinite(obstacles).all():
            raise ValueError("`obstacles` contains NaN or inf at a present slot")
        if self.mode == "goal":
            if goal is None or np.shape(goal) != (2,) or not np.isfinite(goal).all():
                raise ValueError(f"a goal NLP needs a finite `goal` of shape (2,); got {goal!r}")
            goal_values = np.asarray(goal, dtype=float)
        else:
            goal_values = np.zeros(2)
        # CasADi's vec is column-major: (M, K+1) -> stacked columns.
        return np.concatenate([goal_values, obstacles[..., 0].ravel(order="F"), obstacles[..., 1].ravel(order="F")])

    def bounds(self, ego: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(lbx, ubx): knot 0 fixed to ``ego``; speed, heading and road bands widened to include it."""
        ego = np.asarray(ego, dtype=float)
        if ego.shape != (NUM_STATES,) or not np.isfinite(ego).all():
            raise ValueError(f"`ego` must be a finite array of shape (6,); got {ego!r}")
        opt = self.optimizer
        heading = math.radians(opt.max_heading_deg)
        left, right = self.road.bounds
        y_low = min(left + self.road_margin, ego[1])
        y_high = max(right - self.road_margin, ego[1])
        low = np.array([-np.inf, y_low, min(-heading, ego[2]), min(opt.v_min, ego[3]), -np.inf, -np.inf])
        high = np.array([np.inf, y_high, max(heading, ego[2]), max(opt.v_max, ego[3]), np.inf, np.inf])
        knots = self.config.intervals + 1
        lbx_states = np.tile(low, (knots, 1))
        ubx_states = np.tile(high, (knots, 1))
        lbx_states[0] = ubx_states[0] = ego
        controls = NUM_CONTROLS * self.config.intervals
        lbx = np.concatenate([lbx_states.ravel(), np.full(controls, -np.inf)])
        ubx = np.concatenate([ubx_states.ravel(), np.full(controls, np.inf)])
        return lbx, ubx

    def initial_guess(self, ego: np.ndarray, goal: Optional[np.ndarray] = None) -> np.ndarray:
        """Cold start: constant speed straight ahead, or, with a goal, along the straight line to
        it at the average speed that reaches it at ``t_f`` (heading along the road)."""
        ego = np.asarray(ego, dtype=float)
        t = self.times
        states = np.zeros((t.size, NUM_STATES))
        if goal is None:
            speed = max(ego[3], self.optimizer.v_min)
            states[:, 0] = ego[0] + speed * t
            states[:, 1] = ego[1]
        else:
            fraction = t / t[-1]
            states[:, 0] = ego[0] + (goal[0] - ego[0]) * fraction
            states[:, 1] = ego[1] + (goal[1] - ego[1]) * fraction
            speed = float(np.clip((goal[0] - ego[0]) / t[-1], self.optimizer.v_min, self.optimizer.v_max))
        states[:, 3] = speed
        states[0] = ego
        return np.concatenate([states.ravel(), np.zeros(NUM_CONTROLS * self.config.intervals)])

    # ----------------------------------------------------------------------------- solve

    def solve(
        self,
        ego: np.ndarray,
        obstacles: np.ndarray,
        mask: np.ndarray,
        goal: Optional[np.ndarray] = None,
        *,
        initial: Optional[np.ndarray] = None,
        multipliers_g: Optional[np.ndarray] = None,
    ) -> NLPSolution:
        """Solve once.

        Args:
            ego: (6,) start state.
            obstacles: (M, K + 1, 2) predicted obstacle centres at :attr:`times` [m].
            mask: (M,) present slots.
            goal: (2,) end position (``goal`` mode only).
            initial: warm start (a previous :attr:`NLPSolution.primal`, e.g. shifted); default
                :meth:`initial_guess`.
            multipliers_g: constraint multipliers to start from (with ``initial``).

        Returns:
            An :class:`NLPSolution`; ``feasible`` is the recomputed check, not IPOPT's word.
        """
        params = self.parameters(obstacles, mask, goal)
        lbx, ubx = self.bounds(ego)
        if initial is None:
            initial = self.initial_guess(ego, None if goal is None else np.asarray(goal, dtype=float))
        initial = np.clip(np.asarray(initial, dtype=float), lbx, ubx)
        arguments = dict(x0=initial, p=params, lbx=lbx, ubx=ubx, lbg=self._lbg, ubg=self._ubg)
        if multipliers_g is not None:
            arguments["lam_g0"] = multipliers_g
        start = time.perf_counter()
        output = self._solver(**arguments)
        solve_ms = (time.perf_counter() - start) * 1e3
        stats = self._solver.stats()
        primal = np.asarray(output["x"]).ravel()
        violation = self.violation(primal, params, lbx, ubx)
        knots = self.config.intervals + 1
        states = primal[: NUM_STATES * knots].reshape(knots, NUM_STATES)
        controls = primal[NUM_STATES * knots :].reshape(self.config.intervals, NUM_CONTROLS)
        finite = bool(np.isfinite(primal).all())
        return NLPSolution(
            states=states,
            controls=controls,
            status=str(stats.get("return_status", "unknown")),
            iterations=int(stats.get("iter_count", -1)),
            violation=violation,
            feasible=finite and violation <= self.config.feasibility_tolerance,
            objective=float(output["f"]),
            solve_ms=solve_ms,
            primal=primal,
            multipliers_g=np.asarray(output["lam_g"]).ravel(),
        )

    def violation(self, primal: np.ndarray, params: np.ndarray, lbx: np.ndarray, ubx: np.ndarray) -> float:
        """Largest violation of any constraint or bound at ``primal`` (inf if not finite)."""
        values = np.asarray(self._constraints(primal, params)).ravel()
        if not (np.isfinite(values).all() and np.isfinite(primal).all()):
            return float("inf")
        excess = np.concatenate([self._lbg - values, values - self._ubg, lbx - primal, primal - ubx])
        return float(max(excess.max(), 0.0))

    def constraint_values(self, primal: np.ndarray, params: np.ndarray) -> dict[str, np.ndarray]:
        """Constraint values at ``primal`` by group (``dynamics``, ``acceleration``, ``obstacle``,
        ``end_heading`` and, in goal mode, ``goal``)."""
        values = np.asarray(self._constraints(primal, params)).ravel()
        return {name: values[part] for name, part in self.constraint_groups.items()}

    def shift(self, solution: NLPSolution, elapsed: float) -> np.ndarray:
        """A warm start ``elapsed`` seconds later: the solution interpolated at ``t + elapsed``
        (held at its end state beyond the horizon)."""
        later = np.minimum(self.times + elapsed, self.times[-1])
        states = np.stack([np.interp(later, self.times, solution.states[:, i]) for i in range(NUM_STATES)], axis=1)
        mid = 0.5 * (self.times[:-1] + self.times[1:])
        later_mid = np.minimum(mid + elapsed, mid[-1])
        controls = np.stack([np.interp(later_mid, mid, solution.controls[:, i]) for i in range(NUM_CONTROLS)], axis=1)
        return np.concatenate([states.ravel(), controls.ravel()])


def resample(states: np.ndarray, knot_times: np.ndarray, times: torch.Tensor) -> Trajectories:
    """NLP knot states -> :class:`mmpc.Trajectories` at ``times`` (linear interpolation), so that
    the batch optimizer's meta costs and command extraction apply unchanged.

    Args:
        states: (..., K + 1, 6) knot states as :data:`STATE_FIELDS`.
        knot_times: (K + 1,) knot times [s].
        times: (N,) sample times [s].

    Returns:
        Trajectories with fields (..., N): ``xdot = v cos psi``, ``xddot = a cos psi - v omega
        sin psi`` (and the same for y), ``psidot = omega``.
    """
    states = np.asarray(states, dtype=float)
    lead = states.shape[:-2]
    flat = states.reshape(-1, states.shape[-2], NUM_STATES)
    sample = times.detach().cpu().double().numpy()
    fields = np.stack(
        [np.stack([np.interp(sample, knot_times, row[:, i]) for i in range(NUM_STATES)]) for row in flat]
    )  # (B, 6, N)
    fields = torch.as_tensor(fields, dtype=times.dtype).reshape(*lead, NUM_STATES, sample.size)
    x, y, psi, v, a, omega = fields.unbind(dim=-2)
    cos, sin = torch.cos(psi), torch.sin(psi)
    return Trajectories(
        times, x, y, psi, v,
        xdot=v * cos, ydot=v * sin,
        xddot=a * cos - v * omega * sin, yddot=a * sin + v * omega * cos,
        psidot=omega,
    )
