"""highway-env's ``Kinematics`` observation, computed only when asked for and without pandas."""

from __future__ import annotations

import numpy as np
from highway_env.envs.common.observation import KinematicObservation


class DeferredKinematics(KinematicObservation):
    """highway-env's ``Kinematics`` observation (its default features, order and normalisation),
    computed only when asked for.

    highway-env builds its observation on every ``env.step`` through pandas frames (~25 ms of a
    ~45 ms frame here); the worlds step it once per simulation frame and read it once per decision,
    if at all. This observation type answers highway-env's per-frame call with a constant placeholder
    of the right shape, and :meth:`compute` gives highway-env's values from the same neighbours,
    in numpy.

    Args:
        env: the highway-env environment; its ``vehicle`` is the observer.
        vehicles_count: rows, the ego first.
    """

    def __init__(self, env, vehicles_count: int) -> None:
        super().__init__(env, vehicles_count=vehicles_count)
        self._placeholder = np.zeros(self.space().shape, dtype=np.float32)

    def observe(self) -> np.ndarray:
        return self._placeholder.copy()

    def compute(self) -> np.ndarray:
        """The current ``Kinematics`` observation, (vehicles_count, 5) float32: presence, x, y, vx, vy;
        the ego's row absolute, the nearest others' (highway-env's ``close_objects_to``, sorted by
        lane distance) relative to it, each mapped onto [-1, 1] by ``features_range`` and clipped;
        missing rows zero."""
        if not self.env.road:
            return self._placeholder.copy()
        ego = self.observer_vehicle
        close = self.env.road.close_objects_to(ego, self.env.PERCEPTION_DISTANCE, count=self.vehicles_count - 1,
                                               see_behind=self.see_behind, sort=self.order == "sorted",
                                               vehicles_only=not self.include_obstacles)
        origin = _kinematics_row(ego)
        rows = [origin]
        if close:
            rows += [_kinematics_row(other) - origin * [0.0, 1.0, 1.0, 1.0, 1.0] for other in close[-self.vehicles_count + 1:]]
        values = np.array(rows, dtype=np.float64)
        self._set_features_range()
        for column, feature in enumerate(self.features):
            if feature in self.features_range:
                low, high = self.features_range[feature]
                values[:, column] = -1 + (values[:, column] - low) * 2 / (high - low)  # highway-env's lmap onto [-1, 1]
                if self.clip:
                    values[:, column] = np.clip(values[:, column], -1, 1)
        observation = np.zeros((max(self.vehicles_count, len(values)), len(self.features)), dtype=np.float32)
        observation[: len(values)] = values
        return observation

    def _set_features_range(self) -> None:
        """highway-env's default ranges, fixed at the first observation by the observer's lanes (as ``normalize_obs``)."""
        if not self.features_range:
            import pandas as pd

            self.normalize_obs(pd.DataFrame(columns=self.features))


def _kinematics_row(vehicle) -> np.ndarray:
    """(5,) float64 presence, x, y, vx, vy of a highway-env vehicle (its velocity along its heading, as highway-env's ``to_dict``)."""
    return np.array([1.0, vehicle.position[0], vehicle.position[1], vehicle.speed * np.cos(vehicle.heading),
                     vehicle.speed * np.sin(vehicle.heading)])
