"""The safe environments' spaces: what an agent observes and which actions it may take.

Observation: highway-env's ``Kinematics`` observation (``kinematics_vehicles`` rows x presence,
x, y, vx, vy, normalised and clipped to [-1, 1]), flattened, followed (with ``solver_features``)
by (feasible, meta cost, clearance) for each goal of the discrete grid (and for the expert's
choice, with ``expert_action``). Actions: the discrete grid ``lane_offsets x speeds`` (then the
expert action), or Box goals ``[-1, 1]^2`` (lateral target, speed).
"""

from __future__ import annotations

from typing import Any, Optional, Sequence

import numpy as np
import torch
from gymnasium import spaces

from mmpc.rl.config import SafeEnvConfig
from mmpc.rl.safety import FEATURES_PER_GOAL

#: Features per row of highway-env's Kinematics observation (its defaults).
KINEMATICS_FEATURES = ("presence", "x", "y", "vx", "vy")


class WallTime(float):
    """A wall-clock measurement [ms] in ``info``, e.g. ``solve_ms``.

    It is a plain float for every use (logging, arithmetic, JSON) except equality: any two
    ``WallTime`` compare equal. Timings are a property of the machine, not of the environment's
    state, and gymnasium's ``check_env`` requires two steps from the same seed and action to
    return equal ``info`` dicts.
    """

    def __eq__(self, other: object) -> bool:
        return isinstance(other, WallTime) or float.__eq__(self, other)

    def __ne__(self, other: object) -> bool:
        return not self.__eq__(other)

    __hash__ = float.__hash__


def action_space(config: SafeEnvConfig, continuous: bool) -> spaces.Space:
    """Box ``[-1, 1]^2`` goal commands, or the discrete grid ``lane_offsets x speeds`` (then the
    expert action, with ``expert_action``)."""
    if continuous:
        if config.expert_action:
            raise ValueError("env: `expert_action` is a discrete action; continuous goals (SAC) need expert_action: false")
        return spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32)
    return spaces.Discrete(config.num_actions)


def observation_space(config: SafeEnvConfig, *, layer: bool = True) -> spaces.Box:
    """The flat observation: kinematics rows, then (with ``solver_features``, behind the layer
    only: ``layer=False`` is the plain agent's) the goal features."""
    size = config.kinematics_vehicles * len(KINEMATICS_FEATURES)
    if layer and config.solver_features:
        size += config.num_actions * FEATURES_PER_GOAL
    return spaces.Box(-1.0, 1.0, shape=(size,), dtype=np.float32)


def observation_vectors(kinematics: np.ndarray, features: Optional[np.ndarray], config: SafeEnvConfig) -> np.ndarray:
    """(E, rows, 5) Kinematics observations and (E, A, 3) solver features (``None``: observations
    without them, as the plain environments') -> (E, size) float32 observations, clipped to [-1, 1]."""
    expected = (config.kinematics_vehicles, len(KINEMATICS_FEATURES))
    if kinematics.shape[1:] != expected:
        raise RuntimeError(f"the Kinematics observation has shape {kinematics.shape[1:]}; expected {expected}")
    parts = [kinematics.reshape(kinematics.shape[0], -1)]
    if features is not None:
        parts.append(np.asarray(features, dtype=np.float32).reshape(kinematics.shape[0], -1))
    return np.clip(np.concatenate(parts, axis=1), -1.0, 1.0).astype(np.float32)


def check_action(action: Any, config: SafeEnvConfig, continuous: bool) -> Any:
    """``action`` checked against the safe environments' action space: the goal index as an int
    (a Python or numpy integer, or a 0-d integer array: SB3's vectorized environments pass numpy
    int64, ``predict`` of one observation a 0-d array), or the (2,) array of finite numbers
    (values outside [-1, 1] are clipped later).

    Raises:
        ValueError: anything else (a float index such as 2.7, an array of indices, a wrong
            shape, NaN), naming what came and what is expected.
    """
    if continuous:
        try:
            values = np.asarray(action)
        except ValueError as error:  # ragged nesting
            raise ValueError(f"`action` must be an array of 2 numbers; got {action!r}") from error
        if values.dtype.kind not in "iuf":
            raise ValueError(f"`action` must be an array of 2 numbers; got dtype {values.dtype} ({action!r})")
        if values.shape != (2,):
            raise ValueError(f"`action` must have shape (2,); got {values.shape}")
        if not np.isfinite(values).all():
            raise ValueError(f"`action` must be finite numbers (in [-1, 1]); got {values.tolist()}")
        return values
    meaning = "a goal of the grid lane_offsets x speeds" + (
        f", or {config.num_actions - 1}: the expert's choice" if config.expert_action else "")
    return check_index(action, config.num_actions, meaning)


def check_index(action: Any, count: int, meaning: str) -> int:
    """A discrete ``action`` as an int in [0, ``count``): a Python or numpy integer, or a 0-d integer
    array. ``meaning`` says in a refusal what the indices stand for.

    Raises:
        ValueError: anything else (a float, a bool, an array of indices) or an index out of range.
    """
    if isinstance(action, np.ndarray) and action.shape == ():
        action = action[()]
    if isinstance(action, (bool, np.bool_)) or not isinstance(action, (int, np.integer)):
        came = (f"an array of shape {action.shape} and dtype {action.dtype}" if isinstance(action, np.ndarray)
                else f"{action!r} ({type(action).__name__})")
        raise ValueError(f"`action` must be an int in [0, {count}) ({meaning}); got {came}")
    if not 0 <= action < count:
        raise ValueError(f"`action` must be an int in [0, {count}); got {action}")
    return int(action)


def action_tensor(checked: Sequence[Any], continuous: bool) -> torch.Tensor:
    """Checked actions (:func:`check_action`) -> (E, 2) float32 continuous goals or (E,) long goal indices."""
    if continuous:
        return torch.as_tensor(np.asarray(checked, dtype=np.float32))
    return torch.as_tensor(checked, dtype=torch.long)
