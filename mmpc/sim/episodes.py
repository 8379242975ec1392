"""E episodes of one scenario on the batched simulator: the start drawn per seed, one command
per environment per control step, the traffic window, time limits and per-environment resets.

What highway-env's project path does per episode (:class:`mmpc.highway.HighwayEpisode`), for
all environments at once: each control step applies the ego's command for the scenario's
frame (:class:`mmpc.sim.HighwaySimulator`), then moves the vehicles that left the window
(:func:`mmpc.sim.traffic.keep_in_window`); with the scenario's ``traffic.threats`` the cars near
the ego threaten it (:mod:`mmpc.sim.threats`); an episode is over when the ego crashed or its time
reached the scenario's duration.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import operator
from collections.abc import Iterable
from typing import NamedTuple, Optional, Sequence, Union

import torch

from mmpc.problem import require_on_device, usable_device
from mmpc.scenario import ScenarioConfig
from mmpc.sim.config import SimConfig
from mmpc.sim.ego import ego_action
from mmpc.sim.simulator import HighwaySimulator, ThreatDraws, check_command
from mmpc.sim.state import VehicleState, check_state, on_road
from mmpc.sim.threats import Orders
from mmpc.sim.traffic import check_supported, initial_state, keep_in_window, sim_config
from mmpc.solver import execution
from mmpc.traffic_config import Threats

Seeds = Union[Sequence[int], torch.Tensor]

#: The largest seed: seeds are held as int64.
MAX_SEED = 2**63 - 1


class SimEpisodes:
    """E episodes of ``scenario`` stepped together, each from its own seed.

    Args:
        scenario: an IDM-traffic scenario on highway-env's straight highway
            (:func:`mmpc.sim.traffic.check_supported` says why another is refused).
        seeds: E episode seeds, ints in [0, :data:`MAX_SEED`]: a sequence (numpy integers
            included) or a 1-D integer tensor (on ``device``).
        dtype: float32 or float64 state.
        device: where the state lives (default: ``seeds``' device if a tensor, else torch's
            default device); a device this machine can hold data on (not ``meta``).
        compile: run each step as one compiled graph (:func:`compiled_episode_step`; each E compiles
            once: ~4 minutes on two CPU cores the first time, seconds from inductor's cache; on the CPU
            faster than eager at E = 64, slower at E = 1,024).
        fixed_shapes: :attr:`mmpc.sim.SimConfig.fixed_shapes` (a step reads nothing on the host);
            default: when compiled or off the CPU.

    Example:
        >>> from mmpc.scenario import ScenarioConfig
        >>> episodes = SimEpisodes(ScenarioConfig(duration=1.0), seeds=[0, 1, 2])
        >>> episodes.step(torch.zeros(3, 2))
        >>> episodes.time.tolist(), episodes.done.tolist()
        ([0.1, 0.1, 0.1], [False, False, False])
    """

    def __init__(self, scenario: ScenarioConfig, seeds: Seeds, *, dtype: torch.dtype = torch.float32, device=None,
                 compile: bool = False, fixed_shapes: Optional[bool] = None) -> None:
        check_supported(scenario)
        if not isinstance(compile, bool):
            raise ValueError(f"`compile` must be True or False; got {compile!r}")
        #: Whether :meth:`step` runs compiled (:func:`compiled_episode_step`).
        self.compile = compile
        self.scenario = scenario
        if device is None:
            device = seeds.device if isinstance(seeds, torch.Tensor) else torch.get_default_device()
        device = usable_device(device)
        fixed = (self.compile or device.type != "cpu") if fixed_shapes is None else fixed_shapes
        if self.compile and not fixed:
            raise ValueError("a compiled SimEpisodes needs `fixed_shapes` (one graph per step); got fixed_shapes=False")
        self.config = dataclasses.replace(sim_config(scenario), fixed_shapes=bool(fixed))
        self.simulator = HighwaySimulator(self.config, scenario.traffic.threats)
        self.seeds = _int_tensor("seeds", seeds, device, MAX_SEED)
        if self.seeds.numel() == 0:
            raise ValueError("`seeds` must hold at least one seed (E >= 1)")
        self.state: VehicleState = initial_state(scenario, self.seeds, dtype=dtype)
        check_state(self.state, self.config)
        self.steps = torch.zeros_like(self.seeds)
        #: (E, 2) the ego's applied acceleration [m/s^2] and steering [rad] (zero before the first command).
        self.applied = torch.zeros(self.num_envs, 2, dtype=dtype, device=self.seeds.device)
        #: (E, V, 2) the collision pushes [m] the last step applied (:meth:`road_state` ``at_impact``).
        self.pushes = torch.zeros_like(self.state.impact)
        #: (E,) bool, the environment was given a non-finite command: it stopped there and is
        #: :attr:`done` (checked on the device, so that a step reads nothing on the host; a
        #: caller that reads :attr:`done` reads this with it and says so, as
        #: :meth:`mmpc.highway.batched_world.BatchedWorld.status` does).
        self.refused = torch.zeros_like(self.seeds, dtype=torch.bool)
        #: (E,) bool, a frame had more close pairs or lane changers than the simulator's buffers hold
        #: (:meth:`mmpc.sim.HighwaySimulator.advance`; never seen in traffic); read as :attr:`refused`.
        self.overflowed = torch.zeros_like(self.refused)

    @property
    def device(self) -> torch.device:
        """Where the state lives."""
        return self.seeds.device

    @property
    def num_envs(self) -> int:
        return self.seeds.shape[0]

    @property
    def time(self) -> torch.Tensor:
        """(E,) each episode's time [s]."""
        return self.steps.to(self.state.x.dtype) / self.scenario.frequency

    @property
    def crashed(self) -> torch.Tensor:
        """(E,) bool, the ego crashed."""
        return self.state.crashed[:, 0]

    @property
    def on_road(self) -> torch.Tensor:
        """(E,) bool, the ego's centre lies on a lane (highway-env's ``on_road`` of a straight road)."""
        return on_road(self.state.y[:, 0], self.config)

    @property
    def done(self) -> torch.Tensor:
        """(E,) bool, the ego crashed, the scenario's duration is over or the environment was :attr:`refused`."""
        return self.crashed | (self.time >= self.scenario.duration - 1e-9) | self.refused

    def step(self, command: torch.Tensor, running: Optional[torch.Tensor] = None, orders: Optional[Orders] = None) -> None:
        """Apply one control step's commands.

        Args:
            command: (E, 2) the egos' acceleration [m/s^2] and steering [rad], floating point on the
                episodes' device; an environment whose command is not finite stops and is :attr:`refused`.
            running: (E,) bool tensor on the episodes' device, the environments that move; the
                others keep their state (finished episodes in a lockstep batch). Default: all.
            orders: to single cars, (E, V) each, carried out where the rules allow
                (:class:`mmpc.sim.threats.Orders`); default: none.
        """
        if running is not None:
            if not isinstance(running, torch.Tensor) or running.dtype != torch.bool:
                what = f"a {running.dtype} tensor" if isinstance(running, torch.Tensor) else type(running).__name__
                raise TypeError(f"`running` must be a bool tensor of shape ({self.num_envs},); got {what}")
            if running.shape != (self.num_envs,):
                raise ValueError(f"`running` must have shape ({self.num_envs},); got {tuple(running.shape)}")
            require_on_device(self.seeds.device, "the episodes' state", running=running)
        check_command(command, self.state, finite=False)  # read on the device: see :attr:`refused`
        if orders is not None and (orders.lane_change.shape != self.state.x.shape
                                   or orders.speed.shape != self.state.x.shape):
            raise ValueError(f"`orders` must hold (E, V) = {tuple(self.state.x.shape)} lane changes and speeds; got "
                             f"{tuple(orders.lane_change.shape)} and {tuple(orders.speed.shape)}")
        if running is None:
            running = torch.ones_like(self.refused)
        self.state, self.applied, self.steps, self.pushes, self.refused, self.overflowed = self._step(
            self.state, command.to(self.state.x.dtype), running, self.seeds, self.steps, self.applied, self.refused,
            self.overflowed, orders)

    def _step(self, *arguments) -> "EpisodeStep":
        window, frequency = self.scenario.traffic.window, self.scenario.frequency
        if not self.compile:
            return episode_step(self.simulator, window, frequency, *arguments)
        with torch._dynamo.config.patch(recompile_limit=execution.RECOMPILE_LIMIT):
            return compiled_episode_step(self.config, self.simulator.threats, window, frequency)(*arguments)

    def reset(self, envs: Union[Sequence[int], torch.Tensor], seeds: Seeds) -> None:
        """Start new episodes in some environments; the others keep running.

        Args:
            envs: the R environments: distinct indices in [0, E - 1] (ints, or a 1-D integer
                tensor), or an (E,) bool tensor that marks them (e.g. :attr:`done`); tensors on
                the episodes' device.
            seeds: R seeds, one per environment in the order of ``envs`` (as the constructor's).
        """
        device = self.seeds.device
        if isinstance(envs, torch.Tensor) and envs.dtype == torch.bool:
            if envs.shape != (self.num_envs,):
                raise ValueError(f"`envs` as a bool mask must have shape ({self.num_envs},); got {tuple(envs.shape)}")
            require_on_device(device, "the episodes' state", envs=envs)
            envs = envs.nonzero()[:, 0]
        envs = _int_tensor("envs", envs, device, self.num_envs - 1)
        if len(set(envs.tolist())) != envs.numel():
            raise ValueError(f"`envs` must not repeat an environment; got {envs.tolist()}")
        seeds = _int_tensor("seeds", seeds, device, MAX_SEED)
        if seeds.shape != envs.shape:
            raise ValueError(f"`seeds` must hold one seed per environment reset ({envs.numel()}); got {seeds.numel()}")
        fresh = initial_state(self.scenario, seeds, dtype=self.state.x.dtype)
        check_state(fresh, self.config)
        self.state = VehicleState(*(field.index_copy(0, envs, new) for field, new in zip(self.state, fresh)))
        self.seeds = self.seeds.index_copy(0, envs, seeds)
        self.steps = self.steps.index_fill(0, envs, 0)
        self.applied = self.applied.index_fill(0, envs, 0.0)
        self.pushes = self.pushes.index_fill(0, envs, 0.0)
        self.refused = self.refused.index_fill(0, envs, False)
        self.overflowed = self.overflowed.index_fill(0, envs, False)

    def take(self, rows: torch.Tensor) -> "SimEpisodes":
        """Clones of the episodes in ``rows`` that go on from where these are, as new episodes.

        The traffic is a function of the state, the seed and the step (its draws are keyed on
        both), so a clone stepped with the same commands as its original stays equal to it: a
        search can branch an episode into several futures.

        Args:
            rows: (R,) int64 environment indices on the episodes' device, repeats allowed.
        """
        if not isinstance(rows, torch.Tensor) or rows.dim() != 1 or rows.dtype != torch.int64:
            got = f"a {rows.dtype} tensor of shape {tuple(rows.shape)}" if isinstance(rows, torch.Tensor) else type(rows).__name__
            raise ValueError(f"`rows` must be a 1-D int64 tensor of environment indices; got {got}")
        require_on_device(self.seeds.device, "the episodes' state", rows=rows)
        if rows.numel() == 0 or int(rows.min()) < 0 or int(rows.max()) >= self.num_envs:
            raise ValueError(f"`rows` must hold at least one index in [0, {self.num_envs - 1}]; got {rows.tolist()[:8]}")
        clone = copy.copy(self)
        clone.state = VehicleState(*(field.index_select(0, rows) for field in self.state))
        clone.seeds, clone.steps = self.seeds.index_select(0, rows), self.steps.index_select(0, rows)
        clone.applied, clone.pushes = self.applied.index_select(0, rows), self.pushes.index_select(0, rows)
        clone.refused, clone.overflowed = self.refused.index_select(0, rows), self.overflowed.index_select(0, rows)
        return clone

    def road_state(self, *, at_impact: bool = False) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The egos and the other vehicles in the road frame, as the MPC takes them.

        Args:
            at_impact: take back the collision pushes the last step applied (:attr:`pushes`): after
                the step in which an ego crashed, the cars where they met rather than where the
                push left them (the simulator, as highway-env, separates two cars predicted to
                collide by half the minimum translation each, in the frame that marks them crashed).

        Returns:
            ego: (E, 6) as :data:`mmpc.EGO_FIELDS`: x, y [m], psi (direction of motion: heading
                plus the slip angle of the applied steering) [rad], v [m/s], a (applied) [m/s^2],
                psidot (turn rate of the applied steering) [rad/s].
            vehicles: (E, V - 1, 4) the other vehicles' x, y [m], vx, vy [m/s] (along their heading).
            mask: (E, V - 1) bool, the slots that hold a vehicle.
        """
        state = self.state
        x, y = state.x, state.y
        if at_impact:
            x, y = x - self.pushes[..., 0], y - self.pushes[..., 1]
        beta = torch.atan(0.5 * torch.tan(self.applied[:, 1]))
        speed = state.speed[:, 0]
        turn_rate = speed * torch.sin(beta) / (state.length[:, 0] / 2)
        ego = torch.stack([x[:, 0], y[:, 0], state.heading[:, 0] + beta, speed, self.applied[:, 0], turn_rate], dim=1)
        heading, others_speed = state.heading[:, 1:], state.speed[:, 1:]
        vehicles = torch.stack([x[:, 1:], y[:, 1:], others_speed * torch.cos(heading),
                                others_speed * torch.sin(heading)], dim=2)
        return ego, vehicles, state.alive[:, 1:]


class EpisodeStep(NamedTuple):
    """What one control step of :class:`SimEpisodes` changes: the state, the (E, 2) applied ego
    command, the (E,) step counts, the (E, V, 2) pushes applied, the (E,) refused and overflowed flags."""

    state: VehicleState
    applied: torch.Tensor
    steps: torch.Tensor
    pushes: torch.Tensor
    refused: torch.Tensor
    overflowed: torch.Tensor


def episode_step(simulator: HighwaySimulator, window: Optional[tuple[float, float]], frequency: float,
                 state: VehicleState, command: torch.Tensor, running: torch.Tensor, seeds: torch.Tensor,
                 steps: torch.Tensor, applied: torch.Tensor, refused: torch.Tensor, overflowed: torch.Tensor,
                 orders: Optional[Orders] = None) -> EpisodeStep:
    """One control step of E episodes: what :meth:`SimEpisodes.step` runs (eager, or compiled whole
    with ``fullgraph=True``); with ``simulator.config.fixed_shapes`` its shapes are fixed and it reads
    no value on the host.

    Args:
        simulator: the episodes' simulator; ``window``: the traffic's window (behind, ahead) [m] or
            ``None``; ``frequency``: the control frequency [Hz] (names the threats' draws).
        state: the vehicles; command: (E, 2) the egos' acceleration [m/s^2] and steering [rad], the
            state's dtype; running: (E,) bool, the environments that move.
        seeds, steps: (E,) int64; applied: (E, 2); refused, overflowed: (E,) bool (as :class:`SimEpisodes`'s).
        orders: to single cars, or ``None``.

    An environment given a non-finite command does not move and is marked refused.
    """
    finite = torch.isfinite(command).all(dim=1)
    command = torch.where(finite[:, None], command, 0.0)
    moving = running & finite & ~refused
    after, untested = simulator.advance(state, command, ThreatDraws(seeds, steps, frequency), orders)
    if window is not None:
        after = keep_in_window(after, window, seeds, steps, simulator.config)
    step_applied = torch.stack(ego_action(command[:, 0], command[:, 1], state.speed[:, 0], simulator.config), dim=1)
    # The step's one frame applies the pushes pending before it (a scenario's frame is its control step).
    pushes = torch.where((state.impact_pending & state.alive & moving[:, None])[..., None], state.impact, 0.0)
    state = VehicleState(*(torch.where(moving.view(-1, *([1] * (new.dim() - 1))), new, old)
                           for new, old in zip(after, state)))
    return EpisodeStep(state, torch.where(moving[:, None], step_applied, applied), steps + moving.to(steps.dtype),
                       pushes, refused | (running & ~finite), overflowed | (moving & untested))


@functools.lru_cache(maxsize=None)
def compiled_episode_step(config: SimConfig, threats: Optional[Threats], window: Optional[tuple[float, float]],
                          frequency: float):
    """:func:`episode_step` of one simulator through ``torch.compile(fullgraph=True)``, one per
    set of constants (so that every :class:`SimEpisodes` alike shares its compiled graphs), each
    E specialised (``dynamic=False``)."""
    step = functools.partial(episode_step, HighwaySimulator(config, threats), window, frequency)
    return torch.compile(step, fullgraph=True, dynamic=False)


def _int_tensor(name: str, values: Union[Sequence[int], torch.Tensor], device: torch.device, high: int) -> torch.Tensor:
    """(R,) int64 on ``device`` from R ints in [0, high]: a sequence (numpy integers included) or
    a 1-D integer tensor on ``device``; bools, floats and strings are refused, naming ``name``."""
    if isinstance(values, torch.Tensor):
        require_on_device(device, "the episodes' state", **{name: values})
        if values.dim() != 1 or values.dtype == torch.bool or values.is_floating_point() or values.is_complex():
            raise ValueError(f"`{name}` must be a sequence of ints; got a {values.dtype} tensor of shape {tuple(values.shape)}")
        values = values.tolist()
    if isinstance(values, (str, bytes)) or not isinstance(values, Iterable):
        raise ValueError(f"`{name}` must be a sequence of ints; got {values!r}")
    ints = []
    for item in values:
        try:
            number = operator.index(item)  # an int or a numpy integer; not a float, str or numpy bool
        except TypeError:
            number = None
        if number is None or isinstance(item, bool):
            raise ValueError(f"`{name}` must be a sequence of ints; got {item!r} ({type(item).__name__}) in it")
        if number < 0:
            raise ValueError(f"`{name}` must be >= 0; got {number}")
        if number > high:
            raise ValueError(f"`{name}` must lie in [0, {high}]; got {number}")
        ints.append(number)
    return torch.tensor(ints, dtype=torch.int64, device=device)

