"""The batch optimizer's settings (:class:`OptimizerConfig`), validated; loaded from YAML by
:mod:`mmpc.config`'s mechanism."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Optional

from mmpc.config import require, require_field_types


@dataclass(frozen=True)
class OptimizerConfig:
    """Settings of :class:`mmpc.BatchOptimizer`. Defaults are the paper authors' values.

    Attributes:
        horizon: planning horizon t_f [s].
        num_steps: samples N over the horizon (t = 0 and t = t_f included).
        order: Bernstein polynomial order (K = order + 1 coefficients per axis).
        iterations: alternating-minimisation iterations of the schedule (every element's, without
            ``exit_checks``).
        exit_checks: early exit: iterations after which the elements already feasible, and inside
            the backed-off sets the iterations project onto (up to the tolerances), stop and keep
            that iterate; the others run on to the next check and at most ``iterations``;
            strictly increasing, each in [1, iterations), multiples of 10 on the compiled CPU
            path (its unit of compiled iterations). Cold-started solves only (a warm start runs
            the schedule's tail). Empty: every element runs the whole schedule (the paper).
        rho_init: penalty weight of the first iteration [-].
        rho_growth: factor applied to the penalty weight after every iteration [-].
        weight_xy: smoothness weight w of ``w * Pddot^T Pddot`` for x and y [-].
        weight_psi: smoothness weight for the heading [-].
        ellipse_a: obstacle ellipse semi-axis along the road, ego size included [m].
        ellipse_b: obstacle ellipse semi-axis across the road, ego size included [m].
        a_max: bound on the acceleration norm [m/s^2].
        v_min: lower speed bound [m/s].
        v_max: upper speed bound [m/s].
        max_obstacles: largest number of obstacle slots M a problem may carry.
        max_heading_deg: heading band around the road direction; outside it a trajectory is
            infeasible (the paper's assumption 2) [deg].
        heading_target_deg: when set, the heading step clips its targets ``atan2(ydot, xdot)``
            to +-this band, which turns the heading band from a filter on finished trajectories
            into a constraint of the iterations (the NLP baselines bound psi the same way);
            ``None`` leaves the targets unclipped, as in the paper. Set it a little inside
            ``max_heading_deg``: the smooth heading polynomial overshoots clipped targets
            slightly [deg].
        start_acceleration: also constrain the initial acceleration to the ego's current one (held
            to the a_max disc: a harder brake than a plan may use would make every plan infeasible).
        lane_weight: lane keeping, ``lane_weight/2 sum_t s(t) (y(t) - y_goal)^2`` added to the
            lateral smoothness cost, with s rising from 0 at the start to 1 at
            ``lane_settle_time`` (:func:`mmpc.solver.operators.lane_keeping_profile`): the path reaches
            its goal's lane early and stays centred on it rather than drifting across over the
            whole horizon. Soft: the constraint penalties outgrow it as rho grows. 0: the
            paper's cost [1/s^4, like ``weight_xy``'s ``Pddot``].
        lane_settle_time: time by which the lane-keeping weight is full [s].
        obstacle_backoff: the iterations project points onto the ellipses scaled by
            ``1 + obstacle_backoff`` while the feasibility check keeps the true ones: a plan
            still closing in on the larger ellipse after the last iteration is feasible
            already (0: the paper's projection) [-].
        acceleration_backoff: likewise, the iterations project onto the disc of radius
            ``a_max - acceleration_backoff`` [m/s^2].
        obstacle_tolerance: feasible trajectories keep normalised obstacle distance >= 1 - this [-].
        acceleration_tolerance: allowed excess of the acceleration norm over a_max [m/s^2].
        nonholonomic_tolerance: allowed max |(xdot, ydot) - v (cos psi, sin psi)| [m/s].
        speed_tolerance: allowed excess of the path speed |(xdot, ydot)| over [v_min, v_max] [m/s].
    """

    horizon: float = 8.0
    num_steps: int = 100
    order: int = 10
    iterations: int = 100
    exit_checks: tuple[int, ...] = ()
    rho_init: float = 1.0
    rho_growth: float = 1.06
    weight_xy: float = 2.5
    weight_psi: float = 5.0
    ellipse_a: float = 5.6
    ellipse_b: float = 3.0
    a_max: float = 4.0
    v_min: float = 0.1
    v_max: float = 30.0
    max_obstacles: int = 10
    max_heading_deg: float = 13.0
    heading_target_deg: Optional[float] = None
    start_acceleration: bool = True
    lane_weight: float = 0.0
    lane_settle_time: float = 3.0
    obstacle_backoff: float = 0.0
    acceleration_backoff: float = 0.0
    obstacle_tolerance: float = 0.01
    acceleration_tolerance: float = 0.05
    nonholonomic_tolerance: float = 0.1
    speed_tolerance: float = 0.1

    def __post_init__(self) -> None:
        require_field_types(self)
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if isinstance(value, float):
                require(math.isfinite(value), f"`{field.name}` must be finite; got {value}")
        require(self.horizon > 0, f"`horizon` must be > 0 s; got {self.horizon}")
        require(self.num_steps >= 2, f"`num_steps` must be >= 2; got {self.num_steps}")
        require(3 <= self.order <= 30, f"`order` must be in [3, 30]; got {self.order}")
        require(self.iterations >= 1, f"`iterations` must be >= 1; got {self.iterations}")
        checks = list(self.exit_checks)
        require(
            all(0 < k < self.iterations for k in checks) and checks == sorted(set(checks)),
            f"`exit_checks` must be strictly increasing iterations in [1, iterations={self.iterations}); got {checks}",
        )
        require(self.rho_init > 0, f"`rho_init` must be > 0; got {self.rho_init}")
        require(self.rho_growth >= 1, f"`rho_growth` must be >= 1; got {self.rho_growth}")
        require(
            self.rho_init * self.rho_growth ** (self.iterations - 1) < 1e8,
            "`rho_init * rho_growth**(iterations - 1)` must stay below 1e8 (conditioning); "
            f"got {self.rho_init * self.rho_growth ** (self.iterations - 1):.3g}",
        )
        require(self.weight_xy > 0, f"`weight_xy` must be > 0; got {self.weight_xy}")
        require(self.weight_psi > 0, f"`weight_psi` must be > 0; got {self.weight_psi}")
        require(self.lane_weight >= 0, f"`lane_weight` must be >= 0; got {self.lane_weight}")
        require(self.lane_settle_time > 0, f"`lane_settle_time` must be > 0 s; got {self.lane_settle_time}")
        require(0 <= self.obstacle_backoff < 1, f"`obstacle_backoff` must be in [0, 1); got {self.obstacle_backoff}")
        require(
            0 <= self.acceleration_backoff < self.a_max,
            f"`acceleration_backoff` must be in [0, a_max={self.a_max}) m/s^2; got {self.acceleration_backoff}",
        )
        require(self.ellipse_a > 0, f"`ellipse_a` must be > 0 m; got {self.ellipse_a}")
        require(self.ellipse_b > 0, f"`ellipse_b` must be > 0 m; got {self.ellipse_b}")
        require(self.a_max > 0, f"`a_max` must be > 0 m/s^2; got {self.a_max}")
        require(self.v_min >= 0, f"`v_min` must be >= 0 m/s; got {self.v_min}")
        require(
            self.v_max > self.v_min,
            f"`v_max` must exceed `v_min`; got v_min={self.v_min}, v_max={self.v_max}",
        )
        require(self.max_obstacles >= 0, f"`max_obstacles` must be >= 0; got {self.max_obstacles}")
        require(
            0 < self.max_heading_deg < 90,
            f"`max_heading_deg` must be in (0, 90); got {self.max_heading_deg}",
        )
        if self.heading_target_deg is not None:
            require(
                0 < self.heading_target_deg <= self.max_heading_deg,
                f"`heading_target_deg` must be null or in (0, max_heading_deg={self.max_heading_deg}]; "
                f"got {self.heading_target_deg!r}",
            )
        for name in (
            "obstacle_tolerance",
            "acceleration_tolerance",
            "nonholonomic_tolerance",
            "speed_tolerance",
        ):
            require(getattr(self, name) >= 0, f"`{name}` must be >= 0; got {getattr(self, name)}")

    @property
    def ellipse(self) -> tuple[float, float]:
        """The obstacle ellipse's semi-axes (a, b) [m]."""
        return self.ellipse_a, self.ellipse_b

    @property
    def dt(self) -> float:
        """Time between samples [s]."""
        return self.horizon / (self.num_steps - 1)

    def rho_schedule(self) -> list[float]:
        """Penalty weight of each iteration, length ``iterations``."""
        return [self.rho_init * self.rho_growth**k for k in range(self.iterations)]
