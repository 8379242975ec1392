"""Validated configuration of the batch optimizer.

Every field has a unit; :meth:`OptimizerConfig.from_dict` rejects unknown keys so that a
misspelled YAML key is an error, not a silently ignored setting.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Optional, TypeVar

import yaml

T = TypeVar("T")


def dataclass_from_dict(cls: type[T], values: Mapping[str, Any], *, where: str = "") -> T:
    """Build dataclass ``cls`` from ``values``, refusing keys that are not fields of ``cls``."""
    if not isinstance(values, Mapping):
        raise TypeError(f"{where or cls.__name__} must be a mapping; got {type(values).__name__}")
    names = {f.name for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(set(values) - names)
    if unknown:
        raise ValueError(
            f"unknown key(s) {unknown} in {where or cls.__name__}; allowed keys: {sorted(names)}"
        )
    return cls(**values)


def read_config_yaml(name_or_path: str | Path, directory: Path, what: str, listing: str) -> tuple[Path, dict]:
    """Read a YAML config given by a path or by the name of a file shipped in ``directory``.

    Args:
        name_or_path: a path (with a suffix) or a shipped file's stem, e.g. ``"cruise"``.
        directory: the folder of the shipped ``<name>.yaml`` files.
        what: what the file is, for messages (e.g. ``"scenario"``).
        listing: what the shipped files are called in the message (e.g. ``"scenarios"``).

    Returns:
        The resolved path and the parsed values.

    Raises:
        FileNotFoundError: no such file; the message lists the shipped names.
        ValueError: the file is empty (or only comments) or does not hold a mapping: an empty
            file is a mistake, not a request for the defaults.
    """
    path = Path(name_or_path)
    if not path.suffix:
        path = directory / f"{name_or_path}.yaml"
    if not path.is_file():
        shipped = sorted(p.stem for p in directory.glob("*.yaml")) if directory.is_dir() else []
        raise FileNotFoundError(f"{what} {str(name_or_path)!r}: no file {path}; shipped {listing}: {shipped}")
    with open(path, encoding="utf-8") as handle:
        values = yaml.safe_load(handle)
    if values is None:
        raise ValueError(f"{what} file {path} is empty; expected a mapping of settings (key: value lines)")
    if not isinstance(values, dict):
        raise ValueError(f"{what} file {path} must hold a mapping of settings (key: value lines); "
                         f"got a {type(values).__name__}")
    return path, values


def require(condition: bool, message: str) -> None:
    """Raise ``ValueError(message)`` unless ``condition``: the check every config validator uses."""
    if not condition:
        raise ValueError(message)


def is_finite_number(value: Any) -> bool:
    """A real int or float (not a bool) that is neither NaN nor infinite."""
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def require_positive(where: str, **values: Any) -> None:
    """Check that every keyword value is a finite number > 0.

    The message names the field and the value that came: ``"{where}: `name` must be a finite
    number > 0; got value"`` (without the ``where`` prefix when it is empty).
    """
    prefix = f"{where}: " if where else ""
    for name, value in values.items():
        require(is_finite_number(value) and value > 0, f"{prefix}`{name}` must be a finite number > 0; got {value!r}")


def require_non_negative(where: str, **values: Any) -> None:
    """Check that every keyword value is a finite number >= 0 (messages as :func:`require_positive`)."""
    prefix = f"{where}: " if where else ""
    for name, value in values.items():
        require(is_finite_number(value) and value >= 0, f"{prefix}`{name}` must be a finite number >= 0; got {value!r}")


@dataclass(frozen=True)
class OptimizerConfig:
    """Settings of :class:`mmpc.BatchOptimizer`. Defaults are the paper authors' values.

    Attributes:
        horizon: planning horizon t_f [s].
        num_steps: samples N over the horizon (t = 0 and t = t_f included).
        order: Bernstein polynomial order (K = order + 1 coefficients per axis).
        iterations: fixed number of alternating-minimisation iterations.
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
        start_acceleration: also constrain the initial acceleration to the ego's current one.
        obstacle_tolerance: feasible trajectories keep normalised obstacle distance >= 1 - this [-].
        acceleration_tolerance: allowed excess of the acceleration norm over a_max [m/s^2].
        nonholonomic_tolerance: allowed max |(xdot, ydot) - v (cos psi, sin psi)| [m/s].
        speed_tolerance: allowed excess of the path speed |(xdot, ydot)| over [v_min, v_max] [m/s].
    """

    horizon: float = 8.0
    num_steps: int = 100
    order: int = 10
    iterations: int = 100
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
    obstacle_tolerance: float = 0.01
    acceleration_tolerance: float = 0.05
    nonholonomic_tolerance: float = 0.1
    speed_tolerance: float = 0.1

    def __post_init__(self) -> None:
        for name in ("num_steps", "order", "iterations", "max_obstacles"):
            value = getattr(self, name)
            require(
                isinstance(value, int) and not isinstance(value, bool),
                f"`{name}` must be an int; got {value!r}",
            )
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if isinstance(value, float):
                require(math.isfinite(value), f"`{field.name}` must be finite; got {value}")
        require(self.horizon > 0, f"`horizon` must be > 0 s; got {self.horizon}")
        require(self.num_steps >= 2, f"`num_steps` must be >= 2; got {self.num_steps}")
        require(3 <= self.order <= 30, f"`order` must be in [3, 30]; got {self.order}")
        require(self.iterations >= 1, f"`iterations` must be >= 1; got {self.iterations}")
        require(self.rho_init > 0, f"`rho_init` must be > 0; got {self.rho_init}")
        require(self.rho_growth >= 1, f"`rho_growth` must be >= 1; got {self.rho_growth}")
        require(
            self.rho_init * self.rho_growth ** (self.iterations - 1) < 1e8,
            "`rho_init * rho_growth**(iterations - 1)` must stay below 1e8 (conditioning); "
            f"got {self.rho_init * self.rho_growth ** (self.iterations - 1):.3g}",
        )
        require(self.weight_xy > 0, f"`weight_xy` must be > 0; got {self.weight_xy}")
        require(self.weight_psi > 0, f"`weight_psi` must be > 0; got {self.weight_psi}")
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
                isinstance(self.heading_target_deg, (int, float))
                and not isinstance(self.heading_target_deg, bool)
                and 0 < self.heading_target_deg <= self.max_heading_deg,
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
    def dt(self) -> float:
        """Time between samples [s]."""
        return self.horizon / (self.num_steps - 1)

    def rho_schedule(self) -> list[float]:
        """Penalty weight of each iteration, length ``iterations``."""
        return [self.rho_init * self.rho_growth**k for k in range(self.iterations)]

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> "OptimizerConfig":
        """Build from a mapping (e.g. parsed YAML); unknown keys raise ``ValueError``."""
        return dataclass_from_dict(cls, values, where="optimizer config")

    @classmethod
    def from_yaml(cls, path: str | Path) -> "OptimizerConfig":
        """Load a YAML file such as ``configs/optimizer/default.yaml``."""
        with open(path, encoding="utf-8") as handle:
            values = yaml.safe_load(handle) or {}
        return dataclass_from_dict(cls, values, where=f"optimizer config {path}")
