"""The red team: a PPO agent drives one car of the batched simulator's traffic, within the rules,
to make a driver under test collide.

The red car is the car ahead of the ego within :data:`RED_REACH` that the ego comes to first,
counting each lane between them as :data:`LANE_DISTANCE` more road (so mostly the car it follows);
once the ego has passed it by :data:`PASSED` another is picked, so every episode has a car to use. Every control step the agent picks one of :data:`ACTIONS` for it,
given as :class:`mmpc.sim.threats.Orders` and carried out only where the rules allow (a lane
change at the car's MOBIL decision where MOBIL's safety criterion holds, braking and speeding up
as hard as IDM may), so the red car stays inside :class:`mmpc.verify.TrafficAssumptions`; the
other cars drive as the scenario's traffic does. The ego is the driver under test, stepped inside
the environment, so the agent learns against that driver.

Reward per step: :data:`COLLISION_REWARD` when the ego collides, plus ``near_miss`` x (1 - ttc /
:data:`NEAR_MISS_TTC`) while the ego closes on the red car ahead of it with a time to collision ``ttc``
below :data:`NEAR_MISS_TTC` (a near miss on the gap alone paid for driving beside the ego, and the
agent never learned to brake ahead of it), so the agent finds the ego before it learns to hit it.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple, Optional, Sequence

import gymnasium as gym
import numpy as np
import torch
from stable_baselines3.common.vec_env.base_vec_env import VecEnvObs, VecEnvStepReturn

from mmpc.drivers import Driver, Observation
from mmpc.rl.vec_env import TensorVecEnv
from mmpc.scenario import ScenarioConfig, batched_unsupported
from mmpc.sim import SimEpisodes
from mmpc.sim.threats import Orders
from mmpc.verify import AssumptionMonitor

#: The agent's choices for the red car: (lane change, speed) orders of :class:`mmpc.sim.threats.Orders`.
ACTIONS = ((0, 0), (0, -1), (0, 1), (-1, 0), (1, 0))
ACTION_NAMES = ("follow", "brake", "speed up", "change left", "change right")
#: The red car is a car ahead of the ego within this distance along the road [m] ...
RED_REACH = 60.0
#: ... the one the ego comes to first, each lane between them counting as this much more road [m] ...
LANE_DISTANCE = 30.0
#: ... and another is picked once the ego is this far past it [m].
PASSED = 10.0
#: Reward of a collision of the ego: above any episode's near-miss reward (100 steps x ``near_miss``),
#: so a collision, which ends the episode, pays more than circling the ego (at 10 it did not).
COLLISION_REWARD = 100.0
#: The ego closing on the red car with a time to collision below this is a near miss, rewarded in proportion [s].
NEAR_MISS_TTC = 3.0
#: The red car's body within this of the ego's, scaled in the observation [m].
NEAR_MISS_GAP = 10.0
#: Observation: the ego (y, speed, heading), the red car relative to it (dx, dy, speed, lateral
#: speed, gap), the nearest other car relative to the ego (dx, dy, speed difference), time left.
OBSERVATION_SIZE = 12


class RedTeamVecEnv(TensorVecEnv):
    """E red-team environments on one :class:`mmpc.sim.SimEpisodes`, a stable-baselines3 ``VecEnv``.

    Args:
        driver: the driver under test (any :class:`mmpc.drivers.Driver`: ``verified:mpc``, ``mpc``, ...).
        scenario: an IDM-traffic scenario the batched simulator runs; its ``duration`` is the episode.
        num_envs: E.
        seeds: the episodes' seeds, taken in order (an evaluation's named seeds), then the seeds
            after the largest of them; ``None``: drawn from ``seed``'s generator.
        seed: seeds the draws of episode seeds.
        near_miss: weight of the near-miss reward.
    """

    def __init__(self, driver: Driver, scenario: ScenarioConfig, num_envs: int, *, seeds: Optional[Sequence[int]] = None,
                 seed: int = 0, near_miss: float = 0.1) -> None:
        reason = batched_unsupported(scenario)
        if reason is not None:
            raise ValueError(f"scenario {scenario.name!r}: {reason}")
        if not (isinstance(num_envs, int) and num_envs >= 1):
            raise ValueError(f"`num_envs` must be an int >= 1; got {num_envs!r}")
        if seeds is not None and len(seeds) == 0:
            raise ValueError("`seeds` must hold at least one seed, or be None")
        if not (near_miss >= 0 and math.isfinite(near_miss)):
            raise ValueError(f"`near_miss` must be a finite number >= 0; got {near_miss!r}")
        self.driver, self.scenario, self.near_miss = driver, scenario, near_miss
        self._named_seeds = list(seeds) if seeds is not None else None
        self._named_next = 0
        self._rng = np.random.default_rng(seed)
        self._next_id = 0
        self.sim: Optional[SimEpisodes] = None
        self.monitor = AssumptionMonitor(scenario.road, scenario.period)
        observation_space = gym.spaces.Box(-np.inf, np.inf, (OBSERVATION_SIZE,), np.float32)
        self.render_mode = None
        super().__init__(num_envs, observation_space, gym.spaces.Discrete(len(ACTIONS)))
        self._actions = np.zeros(num_envs, dtype=np.int64)

    # ------------------------------------------------------------------ episodes

    def _draw_seeds(self, count: int) -> list[int]:
        if self._named_seeds is None:
            return [int(s) for s in self._rng.integers(0, 2**31 - 1, count)]
        after = max(self._named_seeds) + 1 - len(self._named_seeds)  # past the named seeds: those after the largest
        taken = [self._named_seeds[i] if i < len(self._named_seeds) else after + i
                 for i in range(self._named_next, self._named_next + count)]
        self._named_next += count
        return [int(s) for s in taken]

    def _start(self, rows: torch.Tensor) -> None:
        """Name the new episodes of ``rows`` and pick their red cars."""
        count = rows.numel()
        self.ids = self.ids.index_copy(0, rows, torch.arange(self._next_id, self._next_id + count))  # a new tensor: the
        # driver's warm starts and the monitor hold the last one
        self._next_id += count
        self._pick_red(rows)

    def _pick_red(self, rows: torch.Tensor) -> None:
        """The red cars of ``rows`` (module docstring): the car ahead within :data:`RED_REACH` the ego
        comes to first, each lane between them as :data:`LANE_DISTANCE` more road; else the nearest."""
        ego, vehicles, mask = self.sim.road_state()
        road = self.scenario.road
        dx = vehicles[rows, :, 0] - ego[rows, None, 0]
        lanes = (road.lane_index(vehicles[rows, :, 1]) - road.lane_index(ego[rows, 1])[:, None]).abs()
        score = torch.where((dx > 0) & (dx < RED_REACH), dx + LANE_DISTANCE * lanes, dx.abs() + 1e6)
        score = torch.where(mask[rows], score, torch.full_like(score, math.inf))
        self.red[rows] = score.argmin(dim=1) + 1  # a slot of the state (0 is the ego)

    def _passed(self) -> torch.Tensor:
        """(E,) long: the rows whose ego is :data:`PASSED` beyond its red car, or whose red car left."""
        state, rows = self.sim.state, torch.arange(self.num_envs)
        behind = state.x[rows, self.red] < state.x[:, 0] - PASSED
        return (behind | ~state.alive[rows, self.red]).nonzero()[:, 0]

    def reset(self) -> VecEnvObs:
        seeds = self._draw_seeds(self.num_envs)
        self.sim = SimEpisodes(self.scenario, seeds)
        self.episode_seeds = seeds
        self.ids = torch.zeros(self.num_envs, dtype=torch.long)
        self.red = torch.ones(self.num_envs, dtype=torch.long)
        self._next_id = 0
        self.driver.reset(self.num_envs)
        self.monitor.reset()
        self._start(torch.arange(self.num_envs))
        return self._observe()

    # ------------------------------------------------------------------ stepping

    def step_async(self, actions: np.ndarray) -> None:
        actions = np.asarray(actions).reshape(-1)
        if actions.shape != (self.num_envs,) or not np.all((actions >= 0) & (actions < len(ACTIONS))):
            raise ValueError(f"`actions` must be {self.num_envs} ints in [0, {len(ACTIONS) - 1}]; got {actions!r}")
        self._actions = actions.astype(np.int64)

    def step_wait(self) -> VecEnvStepReturn:
        if self.sim is None:
            raise RuntimeError("call reset() before step()")
        sim, rows = self.sim, torch.arange(self.num_envs)
        ego, vehicles, mask = sim.road_state()
        broke = self.monitor.observe(self.ids, ego, vehicles, mask & ~sim.state.crashed[:, 1:])
        red_broke = broke.gather(1, (self.red - 1)[:, None])[:, 0]
        decision = self.driver.decide(Observation(ego, vehicles, mask, None, self.ids))
        command = torch.stack([decision.acceleration, decision.steering], dim=1).to(sim.state.x.dtype).cpu()
        chosen = torch.as_tensor(np.asarray(ACTIONS)[self._actions])  # (E, 2)
        lane_change = torch.zeros_like(sim.state.lane)
        speed = torch.zeros_like(sim.state.lane)
        lane_change[rows, self.red] = chosen[:, 0]
        speed[rows, self.red] = chosen[:, 1]
        sim.step(command, orders=Orders(lane_change, speed))
        crashed = sim.crashed.clone()
        gap = self._red_gap()
        near = (1.0 - self._red_ttc() / NEAR_MISS_TTC).clamp(0.0, 1.0)
        rewards = (COLLISION_REWARD * crashed.double() + self.near_miss * near.double()).numpy().astype(np.float32)
        red_hit = crashed & (gap <= 0.5)
        done = sim.done.clone()
        observations = self._observe()
        infos: list[dict[str, Any]] = []
        for row in range(self.num_envs):
            info = {"crashed": bool(crashed[row]), "red_hit": bool(red_hit[row]), "gap": float(gap[row]),
                    "red_left_assumptions": bool(red_broke[row]), "episode_seed": self.episode_seeds[row]}
            if bool(done[row]):
                info["terminal_observation"] = observations[row]
                info["TimeLimit.truncated"] = not bool(crashed[row])
            infos.append(info)
        finished = done.nonzero()[:, 0]
        if finished.numel():
            seeds = self._draw_seeds(finished.numel())
            sim.reset(finished, seeds)
            for row, new_seed in zip(finished.tolist(), seeds):
                self.episode_seeds[row] = new_seed
            self._start(finished)
        passed = self._passed()
        if passed.numel():
            self._pick_red(passed)
        if finished.numel() or passed.numel():
            observations = self._observe()
        return observations, rewards, done.numpy(), infos

    def _red_gap(self) -> torch.Tensor:
        """(E,) distance between the red car's body and the ego's, along plus across the road [m]."""
        state, rows = self.sim.state, torch.arange(self.num_envs)
        dx = (state.x[rows, self.red] - state.x[:, 0]).abs() - 0.5 * (state.length[rows, self.red] + state.length[:, 0])
        dy = (state.y[rows, self.red] - state.y[:, 0]).abs() - 0.5 * (state.width[rows, self.red] + state.width[:, 0])
        return dx.clamp_min(0.0) + dy.clamp_min(0.0)

    def _red_ttc(self) -> torch.Tensor:
        """(E,) the ego's time to collision with the red car ahead of it, overlapping across the road,
        at their speeds along the road [s] (inf where the red car is not ahead or the ego not closing)."""
        state, rows = self.sim.state, torch.arange(self.num_envs)
        gap = (state.x[rows, self.red] - state.x[:, 0]) - 0.5 * (state.length[rows, self.red] + state.length[:, 0])
        overlap = (state.y[rows, self.red] - state.y[:, 0]).abs() < 0.5 * (state.width[rows, self.red] + state.width[:, 0])
        along = lambda slot: state.speed[rows, slot] * torch.cos(state.heading[rows, slot])  # noqa: E731
        closing = along(torch.zeros_like(self.red)) - along(self.red)
        ahead = overlap & (state.x[rows, self.red] > state.x[:, 0]) & (closing > 0)
        ttc = gap.clamp_min(0.0) / closing.clamp_min(1e-9)
        return torch.where(ahead, ttc, torch.full_like(ttc, math.inf))

    def _observe(self) -> np.ndarray:
        """(E, :data:`OBSERVATION_SIZE`) float32 observations (module docstring), scaled to about [-1, 1]."""
        state, rows = self.sim.state, torch.arange(self.num_envs)
        lanes = self.sim.config.lanes * self.sim.config.lane_width
        x, y, speed = state.x.double(), state.y.double(), state.speed.double()
        vy = speed * torch.sin(state.heading.double())
        red = self.red
        others = state.alive.clone()
        others[:, 0] = False
        others[rows, red] = False
        distance = torch.where(others, (x - x[:, :1]).abs() + 4 * (y - y[:, :1]).abs(), torch.full_like(x, math.inf))
        near = distance.argmin(dim=1)
        time_left = 1.0 - self.sim.time.double() / self.scenario.duration
        features = torch.stack([
            y[:, 0] / lanes, speed[:, 0] / 30.0, state.heading[:, 0].double(),
            (x[rows, red] - x[:, 0]) / 50.0, (y[rows, red] - y[:, 0]) / 8.0, speed[rows, red] / 30.0, vy[rows, red] / 5.0,
            self._red_gap().double() / NEAR_MISS_GAP,
            (x[rows, near] - x[:, 0]) / 50.0, (y[rows, near] - y[:, 0]) / 8.0, (speed[rows, near] - speed[:, 0]) / 30.0,
            time_left,
        ], dim=1)
        return features.clamp(-3.0, 3.0).float().numpy()


class RedTeamScore(NamedTuple):
    """What a red-team agent achieved against a driver over named seeds.

    Fields:
        episodes: episodes run.
        collisions: episodes in which the ego collided; ``red_collisions`` of them with the red car.
        near_misses: episodes in which the red car's body came within 1 m of the ego's, no collision.
        red_left_assumptions: episodes in which the monitor saw the red car leave its set.
        actions: share of each of :data:`ACTION_NAMES` among the agent's choices.
    """

    episodes: int
    collisions: int
    red_collisions: int
    near_misses: int
    red_left_assumptions: int
    actions: dict[str, float]


def score_red_team(model, driver: Driver, scenario: ScenarioConfig, seeds: Sequence[int], num_envs: int) -> RedTeamScore:
    """Run ``model`` (deterministic) against ``driver`` for one episode per seed of ``seeds``."""
    envs = min(num_envs, len(seeds))
    env = RedTeamVecEnv(driver, scenario, envs, seeds=list(seeds))  # episodes started after the named ones are not counted
    observations = env.reset()
    counted = set(int(s) for s in seeds)
    episodes = collisions = red_collisions = near_misses = left = 0
    closest: dict[int, float] = {}
    broke: dict[int, bool] = {}
    chosen = np.zeros(len(ACTIONS))
    active_seed = list(env.episode_seeds)
    while episodes < len(seeds):
        actions, _ = model.predict(observations, deterministic=True)
        chosen += np.bincount(np.asarray(actions).reshape(-1), minlength=len(ACTIONS))
        observations, _, dones, infos = env.step(actions)
        for row, info in enumerate(infos):
            seed = active_seed[row]
            closest[row] = min(closest.get(row, math.inf), info["gap"])
            broke[row] = broke.get(row, False) or info["red_left_assumptions"]
            if dones[row]:
                if seed in counted and episodes < len(seeds):
                    counted.discard(seed)
                    episodes += 1
                    collisions += info["crashed"]
                    red_collisions += info["red_hit"]
                    near_misses += (not info["crashed"]) and closest[row] < 1.0
                    left += broke[row]
                closest[row], broke[row] = math.inf, False
                active_seed[row] = env.episode_seeds[row]
    shares = chosen / max(chosen.sum(), 1.0)
    return RedTeamScore(episodes, collisions, red_collisions, near_misses, left,
                        {name: round(float(share), 4) for name, share in zip(ACTION_NAMES, shares)})
