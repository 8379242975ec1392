"""Road-frame inputs of the cloned policy, built from what every driver receives
(:class:`mmpc.drivers.Observation`): the ego's road-frame state and the other vehicles'.

Two steps, row by row in plain Python floats (a few tens of microseconds per row: at E = 1, in
the policy's step, far cheaper than dozens of small numpy calls; a training set of 10^4 rows
takes a fraction of a second):

1. :func:`nearest_neighbours` picks the :data:`STORED_NEIGHBOURS` other vehicles nearest to the
   ego in the scaled distance ``r = sqrt((dx / a)^2 + (dy / b)^2)`` with the scenario's obstacle
   ellipse (a, b) (the expert's obstacle ranking, but vehicles behind the ego are kept), sorted
   by ``r``, as (x, y, vx, vy) rows with NaN in empty slots. The demonstrations store these
   rows (``infos["neighbours"]``); :func:`road_features` sorts them again with the policy's
   ellipse (:class:`SceneGeometry`), so a policy trained from a dataset and the policy driving
   see the same order.
2. :func:`road_features` turns the ego state and the first K neighbours into the flat vector
   ``[ e ; n_1 ; ... ; n_K ]`` with

   - ``e = (y - y_lane, y - y_left, y_right - y, psi, v[, a, psidot])``: the lateral offset from
     the nearest lane centre and from the road's left and right edges [m], the heading [rad],
     the speed [m/s], and optionally the command being executed (a [m/s^2], psidot [rad/s]);
   - ``n_k = (1, dx, dy, vx - v cos psi, vy - v sin psi)``: presence, position and velocity
     relative to the ego [m, m/s], all zero for an empty slot;
   - optionally (``lane_slots``) ``[ l_1 ; ... ; l_6 ]``: for the ego's lane and the lanes left and
     right of it, the nearest neighbour ahead and the nearest behind (a vehicle belongs to the
     lane whose centre is nearest), each ``l = (1, dx, dy, dvx, c)`` with the inverse time to
     collision ``c = max(0, -dvx sign(dx)) / max(|dx| - L, 1 m)`` [1/s] (L the scenario's vehicle
     length), all zero when the
     slot is empty or the lane is off the road. These make "the car ahead in my lane is close
     and slower" a few inputs instead of a pattern spread over the sorted list.

The ego's absolute x is left out on purpose: on an endless straight road it only encodes the
distance driven.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np

from mmpc.config import require_int
from mmpc.obstacles.shape import offset_distance_squared
from mmpc.problem import EGO_X, EGO_Y
from mmpc.road import Road
from mmpc.scenario import ScenarioConfig

#: Neighbours recorded per step (``infos["neighbours"]``) and the most a policy may read.
STORED_NEIGHBOURS = 8
#: Per-neighbour features.
NEIGHBOUR_FIELDS = ("present", "dx", "dy", "dvx", "dvy")
#: Lane slots: (lane offset from the ego's lane, ahead) in feature order, and their features.
LANE_SLOTS = tuple((lane, ahead) for lane in (-1, 0, 1) for ahead in (True, False))
LANE_SLOT_FIELDS = ("present", "dx", "dy", "dvx", "inverse_ttc")
_SLOT_KEYS = frozenset(LANE_SLOTS)


@dataclass(frozen=True)
class SceneGeometry:
    """What the features take from the scenario besides the road (:func:`scene_geometry`).

    Attributes:
        vehicle_length: length of every vehicle, subtracted from the gap in the inverse time to
            collision [m].
        ellipse: the obstacle ellipse's semi-axes (a, b), the units of the neighbour ranking [m].
    """

    vehicle_length: float
    ellipse: tuple[float, float]

    def __post_init__(self) -> None:
        if not (isinstance(self.vehicle_length, (int, float)) and 0 < self.vehicle_length < math.inf):
            raise ValueError(f"`vehicle_length` must be a finite length > 0 m; got {self.vehicle_length!r}")
        if not (isinstance(self.ellipse, tuple) and len(self.ellipse) == 2 and all(0 < v < math.inf for v in self.ellipse)):
            raise ValueError(f"`ellipse` must be two finite semi-axes > 0 m (a, b); got {self.ellipse!r}")


def scene_geometry(scenario: ScenarioConfig) -> SceneGeometry:
    """The scenario's vehicle length and obstacle ellipse."""
    return SceneGeometry(scenario.vehicle[0], scenario.optimizer.ellipse)


#: The geometry of the policies trained before the features read the scenario (highway-env's
#: 5 m cars and the (8, 3) m ellipse every feature used then); a checkpoint without a ``scene``
#: has it (:data:`mmpc.imitation.policy.POLICY_CHECKPOINT`).
LEGACY_SCENE = SceneGeometry(5.0, (8.0, 3.0))


@dataclass(frozen=True)
class FeatureConfig:
    """Which road-frame features the policy reads (see the module docstring).

    Attributes:
        scene: the scenario's vehicle length and ellipse.
        neighbours: K nearest other vehicles read, 0 <= K <= :data:`STORED_NEIGHBOURS` [-].
        ego_command: also read the command the ego is executing (a [m/s^2], psidot [rad/s]).
        lane_slots: also read the nearest neighbour ahead and behind in the ego's and the
            adjacent lanes.
    """

    scene: SceneGeometry
    neighbours: int = STORED_NEIGHBOURS
    ego_command: bool = False
    lane_slots: bool = False

    def __post_init__(self) -> None:
        if not isinstance(self.scene, SceneGeometry):
            raise ValueError(f"`scene` must be a SceneGeometry; got {type(self.scene).__name__}")
        require_int("", low=0, high=STORED_NEIGHBOURS, neighbours=self.neighbours)
        for name in ("ego_command", "lane_slots"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"`{name}` must be true or false; got {getattr(self, name)!r}")

    @property
    def size(self) -> int:
        """D, the length of the feature vector."""
        return (5 + (2 if self.ego_command else 0) + len(NEIGHBOUR_FIELDS) * self.neighbours
                + (len(LANE_SLOTS) * len(LANE_SLOT_FIELDS) if self.lane_slots else 0))

    def names(self) -> list[str]:
        """The D feature names, in order."""
        ego = ["lane_offset", "left_edge", "right_edge", "psi", "v"] + (["a", "psidot"] if self.ego_command else [])
        slots = [f"lane{lane:+d}_{'ahead' if ahead else 'behind'}_{field}" for lane, ahead in LANE_SLOTS
                 for field in LANE_SLOT_FIELDS] if self.lane_slots else []
        return ego + [f"n{k}_{field}" for k in range(self.neighbours) for field in NEIGHBOUR_FIELDS] + slots


def nearest_neighbours(ego: np.ndarray, vehicles: np.ndarray, mask: Optional[np.ndarray] = None,
                       count: int = STORED_NEIGHBOURS, *, ellipse: tuple[float, float]) -> np.ndarray:
    """The ``count`` other vehicles nearest to the ego (scaled distance, see the module docstring).

    Args:
        ego: (E, 6) ego states as :data:`mmpc.EGO_FIELDS`.
        vehicles: (E, V, 4) other vehicles' x, y [m], vx, vy [m/s] in the road frame.
        mask: (E, V) bool, True for real vehicles; ``None``: all real.
        count: slots to fill.
        ellipse: the scenario's obstacle ellipse (a, b), the distance units [m].

    Returns:
        (E, count, 4) float32, nearest first (ties: in the order of ``vehicles``); NaN rows where
        fewer vehicles exist.
    """
    ego, vehicles = np.asarray(ego), np.asarray(vehicles)
    if ego.ndim != 2 or ego.shape[1] != 6 or vehicles.ndim != 3 or vehicles.shape[0] != ego.shape[0] or vehicles.shape[2] != 4:
        raise ValueError(f"`ego` must be (E, 6) and `vehicles` (E, V, 4); got {ego.shape} and {vehicles.shape}")
    masks = [None] * ego.shape[0] if mask is None else np.asarray(mask, dtype=bool).tolist()
    empty = [math.nan] * 4
    rows = []
    for state, others, real in zip(ego.tolist(), vehicles.tolist(), masks):
        x, y = state[EGO_X], state[EGO_Y]
        ranked = sorted((offset_distance_squared(o[0] - x, o[1] - y, ellipse), i) for i, o in enumerate(others)
                        if (real is None or real[i]) and all(math.isfinite(value) for value in o))
        chosen = [others[i] for _, i in ranked[:count]]
        rows.append(chosen + [empty] * (count - len(chosen)))
    return np.array(rows, dtype=np.float32).reshape(ego.shape[0], count, 4)


def road_features(ego: np.ndarray, neighbours: np.ndarray, road: Road, config: FeatureConfig) -> np.ndarray:
    """The policy's input vector (see the module docstring).

    Args:
        ego: (E, 6) ego states as :data:`mmpc.EGO_FIELDS`.
        neighbours: (E, K', 4) from :func:`nearest_neighbours` (NaN rows: empty slots), K' >=
            ``config.neighbours`` (the lane slots search all K'); read nearest first in
            ``config.scene.ellipse``, whatever ellipse ranked them.
        road: the road (lane centres and edges).
        config: which features, and the scene geometry.

    Returns:
        (E, D) float32 with D = ``config.size``.
    """
    ego = np.asarray(ego, dtype=np.float64)
    neighbours = np.asarray(neighbours, dtype=np.float64)
    if ego.ndim != 2 or ego.shape[1] != 6:
        raise ValueError(f"`ego` must have shape (E, 6); got {ego.shape}")
    if neighbours.ndim != 3 or neighbours.shape[0] != ego.shape[0] or neighbours.shape[2] != 4 \
            or neighbours.shape[1] < config.neighbours:
        raise ValueError(f"`neighbours` must have shape ({ego.shape[0]}, >= {config.neighbours}, 4); got {neighbours.shape}")
    if not np.isfinite(ego).all():
        raise ValueError("road features are not finite: the ego state holds NaN or inf")
    rows = [_row_features(state, near, road, config) for state, near in zip(ego.tolist(), neighbours.tolist())]
    return np.array(rows, dtype=np.float32).reshape(ego.shape[0], config.size)


def _row_features(state: list[float], near: list[list[float]], road: Road, config: FeatureConfig) -> list[float]:
    """The D features of one ego state (6 floats) and its K' neighbours (NaN rows: empty)."""
    x, y, psi, v, a, psidot = state
    width = road.lane_width
    lane = min(max(round(y / width), 0), road.num_lanes - 1)
    left, right = road.bounds
    vx, vy = v * math.cos(psi), v * math.sin(psi)
    features = [y - lane * width, y - left, right - y, psi, v]
    if config.ego_command:
        features += [a, psidot]
    near = sorted(near, key=lambda n: offset_distance_squared(n[0] - x, n[1] - y, config.scene.ellipse)
                  if all(math.isfinite(value) for value in n) else math.inf)
    present = [all(math.isfinite(value) for value in n) for n in near]
    for (nx, ny, nvx, nvy), here in zip(near[:config.neighbours], present):
        features += [1.0, nx - x, ny - y, nvx - vx, nvy - vy] if here else [0.0] * len(NEIGHBOUR_FIELDS)
    if config.lane_slots:
        nearest: dict[tuple[int, bool], tuple[float, float, float]] = {}
        for (nx, ny, nvx, _), here in zip(near, present):
            if not here:
                continue
            dx = nx - x
            key = (round(ny / width) - lane, dx >= 0)
            if key in _SLOT_KEYS and (key not in nearest or abs(dx) < abs(nearest[key][0])):
                nearest[key] = (dx, ny - y, nvx - vx)
        for key in LANE_SLOTS:
            if key in nearest:
                dx, dy, dvx = nearest[key]
                sign = (dx > 0) - (dx < 0)
                features += [1.0, dx, dy, dvx, max(0.0, -dvx * sign) / max(abs(dx) - config.scene.vehicle_length, 1.0)]
            else:
                features += [0.0] * len(LANE_SLOT_FIELDS)
    return features
