"""The simulator: one ego command per environment, all vehicles stepped at once."""

from __future__ import annotations

from typing import NamedTuple, Optional

import torch

from mmpc.sim.collision import handle_collisions
from mmpc.sim.config import SimConfig
from mmpc.sim.ego import ego_action
from mmpc.sim.idm import traffic_command
from mmpc.sim.kinematics import bicycle_step
from mmpc.sim.mobil import advance_timers, change_lanes
from mmpc.sim.state import VehicleState, check_state
from mmpc.sim.threats import Orders, obey_lanes, obey_speeds, threaten_lanes, threaten_speeds
from mmpc.traffic_config import Threats


#: What an overflow of the simulator's buffers means (:meth:`HighwaySimulator.advance`), for the errors that report it.
OVERFLOW = ("had more close pairs or lane changers than the simulator's buffers hold (mmpc.sim.collision.PAIRS_PER_ENV, "
            "mmpc.sim.idm.CHANGES_PER_ENV): the step is not exact")


class ThreatDraws(NamedTuple):
    """What names a step's draws of threatening traffic: (E,) int64 episode ``seeds`` and
    control ``step`` counts, and the scenario's control ``frequency`` [Hz]."""

    seeds: torch.Tensor
    step: torch.Tensor
    frequency: float


class HighwaySimulator:
    """E highway environments x V vehicles stepped together, as highway-env steps one.

    Each frame: every IDM vehicle decides from the current state (its target lane by MOBIL,
    :func:`mmpc.sim.mobil.change_lanes`; then IDM behind its vehicle ahead and lane keeping
    towards the target lane), the ego holds its command, all vehicles move
    (:func:`mmpc.sim.kinematics.bicycle_step`) and their lane-change timers grow, then every
    pair is checked for collisions (:func:`mmpc.sim.collision.handle_collisions`).

    Args:
        config: road, model and behaviour constants; ``config.dt`` is the frame.
        threats: the cars near the ego threaten it within the rules (:mod:`mmpc.sim.threats`:
            cut-ins after MOBIL's decisions, braking and overtaking over IDM's commands);
            :meth:`advance` then needs the step's :class:`ThreatDraws`. ``None``: naturalistic.

    Example:
        >>> from mmpc.sim import vehicle_state
        >>> simulator = HighwaySimulator()
        >>> state = vehicle_state(torch.tensor([[0.0, 40.0]]), torch.tensor([[4.0, 4.0]]), speed=20.0,
        ...                       target_speed=torch.tensor([[20.0, 15.0]]))
        >>> state = simulator.step(state, torch.tensor([[1.0, 0.0]]))   # (E, 2): acceleration, steering
        >>> round(float(state.x[0, 0]), 3), round(float(state.speed[0, 0]), 3)
        (2.0, 20.1)
    """

    def __init__(self, config: SimConfig = SimConfig(), threats: Optional[Threats] = None) -> None:
        if not isinstance(config, SimConfig):
            raise TypeError(f"`config` must be a SimConfig; got {type(config).__name__}")
        if threats is not None and not isinstance(threats, Threats):
            raise TypeError(f"`threats` must be a mmpc.traffic_config.Threats or None; got {type(threats).__name__}")
        self.config = config
        self.threats = threats

    def step(self, state: VehicleState, command: torch.Tensor) -> VehicleState:
        """One ego command, held for ``config.frames_per_command`` frames; inputs checked first.

        Args:
            state: the vehicles (slot 0 the ego), checked with :func:`mmpc.sim.state.check_state`.
            command: (E, 2) the ego's acceleration [m/s^2] and steering [rad], any floating
                dtype (cast to the state's), on the state's device, finite.

        Returns:
            The state after the command's frames.
        """
        check_state(state, self.config)
        check_command(command, state)
        state, untested = self.advance(state, command.to(state.x.dtype))
        if bool(untested.any()):
            raise RuntimeError(f"environments {untested.nonzero()[:5, 0].tolist()} {OVERFLOW}")
        return state

    def advance(self, state: VehicleState, command: torch.Tensor, draws: Optional[ThreatDraws] = None,
                orders: Optional[Orders] = None) -> tuple[VehicleState, torch.Tensor]:
        """:meth:`step` without the checks (with ``config.fixed_shapes``: at fixed shapes, nothing read
        on the host); ``draws`` name the threats' draws (needed with ``threats``); ``orders`` to single cars are
        carried out where the rules allow (:mod:`mmpc.sim.threats`). Returns the state and (E,)
        bool: a frame overflowed a buffer that must hold everything (close pairs, lane changers:
        :func:`mmpc.sim.collision.pair_collisions`, :func:`mmpc.sim.idm.traffic_command`)."""
        if self.threats is not None and draws is None:
            raise ValueError("a simulator with `threats` needs the step's ThreatDraws (seeds, step, frequency)")
        acceleration, steering = ego_action(command[:, 0], command[:, 1], state.speed[:, 0], self.config)
        moving_forward = state.speed[:, 0] >= 0
        untested = torch.zeros_like(moving_forward)
        for _ in range(self.config.frames_per_command):
            state, untested_now = self.frame(state, acceleration, steering, draws, orders)
            untested = untested | untested_now
        ego_speed = torch.where(moving_forward & (state.speed[:, 0] < 0), 0.0, state.speed[:, 0])
        return state._replace(speed=torch.cat([ego_speed[:, None], state.speed[:, 1:]], dim=1)), untested

    def frame(self, state: VehicleState, ego_acceleration: torch.Tensor, ego_steering: torch.Tensor,
              draws: Optional[ThreatDraws] = None, orders: Optional[Orders] = None) -> tuple[VehicleState, torch.Tensor]:
        """One simulation frame with the ego's applied (acceleration [m/s^2], steering [rad]), each (E,);
        returns the state and (E,) bool, a buffer overflowed (:meth:`advance`)."""
        state = change_lanes(state, self.config)
        threats = self.threats
        if threats is not None:
            state = threaten_lanes(state, threats, draws.seeds, draws.step, self.config)
        if orders is not None:
            state = obey_lanes(state, orders, self.config)
        acceleration, steering, unasked = traffic_command(state, self.config)
        if threats is not None:
            acceleration = threaten_speeds(state, acceleration, threats, draws.seeds, draws.step, draws.frequency,
                                           self.config)
        if orders is not None:
            acceleration = obey_speeds(state, acceleration, orders, self.config)
        acceleration = torch.cat([ego_acceleration[:, None], acceleration[:, 1:]], dim=1)
        steering = torch.cat([ego_steering[:, None], steering[:, 1:]], dim=1)
        state = advance_timers(bicycle_step(state, acceleration, steering, self.config), self.config)
        state, untested = handle_collisions(state, self.config.dt, self.config.fixed_shapes)
        return state, untested | unasked


def check_command(command: torch.Tensor, state: VehicleState, *, finite: bool = True) -> None:
    """Refuse (``ValueError`` saying what came) an ego command that is not a floating (E, 2) tensor
    on the state's device, E as the state's, and (``finite``: one value read on the host) finite."""
    num_envs = state.x.shape[0]
    if not isinstance(command, torch.Tensor) or not command.is_floating_point():
        got = command.dtype if isinstance(command, torch.Tensor) else type(command).__name__
        raise ValueError(f"`command` must be a floating-point tensor of shape (E, 2); got {got}")
    if command.dim() != 2 or command.shape[1] != 2:
        raise ValueError(f"`command` must have shape (E, 2) (acceleration, steering); got {tuple(command.shape)}")
    if command.shape[0] != num_envs:
        raise ValueError(f"`command` has {command.shape[0]} environments; the state has E = {num_envs}")
    if command.device != state.x.device:
        raise ValueError(f"`command` is on {command.device}; the state is on {state.x.device}")
    if finite and not bool(torch.isfinite(command).all()):
        bad = torch.nonzero(~torch.isfinite(command).all(dim=1))[:5, 0].tolist()
        raise ValueError(f"`command` must be finite; NaN or inf in environments {bad}")
