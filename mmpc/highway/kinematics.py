"""highway-env's ``Kinematics`` observation, computed only when asked for."""

from __future__ import annotations

import numpy as np
from highway_env.envs.common.observation import KinematicObservation


class DeferredKinematics(KinematicObservation):
    """highway-env's ``Kinematics`` observation, computed only when asked for.

    highway-env builds its observation (a pandas frame, ~14 ms here) on every ``env.step``; the
    safe environments step it once per simulation frame but observe once per agent step. This
    observation type answers highway-env's per-frame call with a constant placeholder of the
    right shape and computes the real observation in :meth:`compute`.
    """

    def __init__(self, env, vehicles_count: int) -> None:
        super().__init__(env, vehicles_count=vehicles_count)
        self._placeholder = np.zeros(self.space().shape, dtype=np.float32)

    def observe(self) -> np.ndarray:
        return self._placeholder.copy()

    def compute(self) -> np.ndarray:
        """The current ``Kinematics`` observation, (vehicles_count, 5) float32."""
        return np.asarray(super().observe(), dtype=np.float32)
