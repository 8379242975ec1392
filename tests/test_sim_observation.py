"""mmpc.sim.observation against highway-env's own ``KinematicObservation``: random scenes placed
in highway-v0 (vehicles behind the ego, beyond the perception distance, dead slots, fewer
vehicles than rows, off the road, ties), the perception borders, real traffic, refused input.

highway-env is imported here only (the observation itself does not import it)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

gym = pytest.importorskip("gymnasium")
highway_env = pytest.importorskip("highway_env")
from gymnasium import spaces  # noqa: E402
from highway_env.envs.common.observation import KinematicObservation  # noqa: E402
from highway_env.vehicle.kinematics import Vehicle  # noqa: E402

from mmpc.highway import HighwayEpisode  # noqa: E402
from mmpc.highway.episode import env_config  # noqa: E402
from mmpc.highway.kinematics import DeferredKinematics  # noqa: E402
from mmpc.scenario import EgoConfig, ScenarioConfig, load_scenario  # noqa: E402
from mmpc.traffic_config import IDMTraffic, ScriptedTraffic  # noqa: E402
from mmpc.sim import SimConfig, VehicleState, kinematics_observation, vehicle_state  # noqa: E402
from mmpc.sim.observation import FEATURES  # noqa: E402

LANE_COUNTS = (3, 4, 6)
ROW_COUNTS = (5, 7)
#: Random scenes per (lanes, rows): (environments, slots); 2 slots leave fewer vehicles than rows.
SCENE_BATCHES = ((30, 12), (10, 2))
#: float64 against highway-env's float64 values (before its cast to float32): only the last bit
#: of cos / sin may differ between torch and numpy (measured at worst: 1.1e-16).
FLOAT64_TOLERANCE = 1e-12
#: float32 against highway-env's float32 observation: both round float64 values within 1e-16 of
#: each other, so at most one float32 step apart (2^-24 for values in [0.5, 1]; measured: 0).
FLOAT32_TOLERANCE = float(np.finfo(np.float32).eps)


class Float64Kinematics(KinematicObservation):
    """highway-env's observation without its final cast to float32 (the dtype of its space)."""

    def space(self) -> spaces.Space:
        return spaces.Box(shape=(self.vehicles_count, len(self.features)), low=-np.inf, high=np.inf, dtype=np.float64)


@pytest.fixture(scope="module")
def highway_envs():
    """lanes -> a highway-v0 environment as the project configures it, without other vehicles."""
    envs = {}
    for lanes in LANE_COUNTS:
        scenario = ScenarioConfig(name="observation", lanes=lanes, traffic=ScriptedTraffic(), ego=EgoConfig(lane=0))
        envs[lanes] = gym.make("highway-v0", config=env_config(scenario))
        envs[lanes].reset(seed=0)
    yield envs
    for env in envs.values():
        env.close()


def highway_env_observations(env, state: VehicleState, environment: int, rows: int) -> tuple[np.ndarray, np.ndarray]:
    """Place environment ``environment`` of ``state`` in ``env`` (slot 0 as its ego, the alive
    slots as the road's other vehicles, in slot order) and observe it: (rows, 5) as highway-env
    returns it (float32) and in float64."""
    unwrapped = env.unwrapped
    road, ego = unwrapped.road, unwrapped.vehicle
    x, y, heading, speed = (getattr(state, name)[environment].double().tolist() for name in ("x", "y", "heading", "speed"))
    alive = state.alive[environment].tolist()
    ego.position, ego.heading, ego.speed = np.array([x[0], y[0]]), heading[0], speed[0]
    ego.LENGTH = float(state.length[environment, 0])
    ego.on_state_update()  # lane_index from the road network
    road.vehicles = [ego] + [Vehicle(road, [x[i], y[i]], heading[i], speed[i]) for i in range(1, len(x)) if alive[i]]
    return (KinematicObservation(unwrapped, vehicles_count=rows).observe(),
            Float64Kinematics(unwrapped, vehicles_count=rows).observe())


def random_scenes(lanes: int, environments: int, slots: int, generator: torch.Generator) -> VehicleState:
    """float64 scenes of float32-representable values (so a float32 copy is the same scene).

    Distances lie on a 0.5 m grid and a third of the vehicles copy the previous slot's distance,
    ahead or behind, so ties and the exact 200 m and two-length borders occur; half the
    environments spread their vehicles over +-60 m (more seen than rows), half over +-260 m
    (beyond the perception distance); y reaches 7 m beyond both road edges; a quarter of the
    slots are dead; the ego's length is 4 to 6 m."""
    shape = (environments, slots)

    def uniform(low: float, high: float, size=shape) -> torch.Tensor:
        return low + (high - low) * torch.rand(size, generator=generator, dtype=torch.float64)

    def chance(probability: float, size=shape) -> torch.Tensor:
        return torch.rand(size, generator=generator) < probability

    spread = torch.where(chance(0.5, (environments, 1)), 60.0, 260.0).double()
    dx = torch.round(uniform(-1.0, 1.0) * spread * 2.0) / 2.0
    copied = chance(0.3) & (torch.arange(slots) >= 2)
    dx = torch.where(copied, torch.where(chance(0.5), 1.0, -1.0).double() * dx.roll(1, dims=1), dx)
    dx[:, 0] = 0.0
    x = torch.round(uniform(-250.0, 1500.0, (environments, 1)) * 2.0) / 2.0 + dx
    y = torch.round(uniform(-7.0, 4.0 * (lanes - 1) + 7.0) * 4.0) / 4.0
    heading = torch.where(chance(0.8), 0.15 * torch.randn(shape, generator=generator, dtype=torch.float64), uniform(-math.pi, math.pi))
    speed = uniform(-10.0, 45.0)
    length = torch.full(shape, 5.0, dtype=torch.float64)
    length[:, 0] = torch.round(uniform(4.0, 6.0, (environments,)) * 2.0) / 2.0
    alive = chance(0.75)
    alive[:, 0] = True
    return vehicle_state(*(value.float().double() for value in (x, y, heading, speed)), config=SimConfig(lanes=lanes),
                         length=length, alive=alive)


def as_float32(state: VehicleState) -> VehicleState:
    """The same scene in float32 (exact: ``random_scenes`` draws float32-representable values)."""
    return state._replace(**{name: getattr(state, name).float() for name in
                             ("x", "y", "heading", "speed", "length", "width", "target_speed", "idm_delta", "impact")})


def coverage(state: VehicleState, lanes: int, rows: int) -> dict[str, int]:
    """How often each case the comparison should include occurs in ``state`` (float64)."""
    dx, dy = state.x[:, 1:] - state.x[:, :1], state.y[:, 1:] - state.y[:, :1]
    alive, near = state.alive[:, 1:], torch.hypot(dx, dy) < 200.0
    behind_limit = -2.0 * state.length[:, :1]
    seen = alive & near & (dx > behind_limit)
    seen_count = seen.sum(dim=1)
    distance = torch.where(seen, dx.abs(), torch.nan)
    return {
        "seen behind": int((seen & (dx < 0)).sum()),
        "hidden behind": int((alive & near & (dx <= behind_limit)).sum()),
        "beyond 200 m": int((alive & ~near).sum()),
        "dead slots": int((~alive).sum()),
        "fewer seen than rows": int((seen_count < rows - 1).sum()),
        "more seen than rows": int((seen_count > rows - 1).sum()),
        "off the road": int((alive & ((state.y[:, 1:] < -2.0) | (state.y[:, 1:] > 4.0 * lanes - 2.0))).sum()),
        "ties": int((distance[:, :, None] == distance[:, None, :]).triu(diagonal=1).sum()),
    }


@pytest.mark.parametrize("rows", ROW_COUNTS)
@pytest.mark.parametrize("lanes", LANE_COUNTS)
def test_random_scenes_equal_highway_env_s(highway_envs, lanes, rows):
    generator = torch.Generator().manual_seed(100 * lanes + rows)
    worst = {torch.float64: 0.0, torch.float32: 0.0}
    cases = {}
    for environments, slots in SCENE_BATCHES:
        state = random_scenes(lanes, environments, slots, generator)
        for name, count in coverage(state, lanes, rows).items():
            cases[name] = cases.get(name, 0) + count
        exact = kinematics_observation(state, SimConfig(lanes=lanes), vehicles_count=rows)
        single = kinematics_observation(as_float32(state), SimConfig(lanes=lanes), vehicles_count=rows)
        assert exact.shape == single.shape == (environments, rows, len(FEATURES))
        assert exact.dtype == torch.float64 and single.dtype == torch.float32
        for environment in range(environments):
            expected32, expected64 = highway_env_observations(highway_envs[lanes], state, environment, rows)
            np.testing.assert_array_equal(exact[environment, :, 0].numpy(), expected64[:, 0])  # the same rows present
            worst[torch.float64] = max(worst[torch.float64], float(np.abs(exact[environment].numpy() - expected64).max()))
            worst[torch.float32] = max(worst[torch.float32], float(np.abs(single[environment].numpy() - expected32).max()))
    assert min(cases.values()) > 0, cases
    assert worst[torch.float64] <= FLOAT64_TOLERANCE and worst[torch.float32] <= FLOAT32_TOLERANCE, worst


def test_perception_borders_norm_and_ties(highway_envs):
    """Ego at (100, 4) m, 5 m long, on 6 lanes (y range +-24 m); one row per seen vehicle and one more."""
    slots = [  # (x, y) [m], what highway-env decides
        (100.0, 4.0),  # the ego
        (299.5, 4.0),  # seen: 199.5 m
        (300.0, 4.0),  # not seen: exactly 200 m (strict)
        (299.0, 12.0),  # seen: 199.2 m by the Euclidean norm (207 m by the L1 norm)
        (299.9, -8.0),  # not seen: 200.26 m (199.9 m by the max norm)
        (220.0, 164.0),  # not seen: exactly 200 m, (120, 160) m away
        (90.0, 4.0),  # not seen: exactly two lengths behind (strict)
        (109.5, 8.0),  # seen: 9.5 m ahead, ties with the next one and comes first (slot order)
        (90.5, 0.0),  # seen: 9.5 m behind
        (100.0, 8.0),  # seen: alongside, ties with the next one
        (100.0, 0.0),  # seen: alongside
        (101.0, 4.0),  # dead
    ]
    x, y = torch.tensor([slots], dtype=torch.float64).unbind(dim=2)
    alive = torch.ones_like(x, dtype=torch.bool)
    alive[0, -1] = False
    state = vehicle_state(x, y, speed=20.0, alive=alive, config=SimConfig(lanes=6))
    observation = kinematics_observation(state, SimConfig(lanes=6), vehicles_count=8)[0]
    assert observation[:, 0].tolist() == [1.0] * 7 + [0.0]
    np.testing.assert_allclose(observation[1:7, 1].numpy() * 200.0, [0.0, 0.0, 9.5, -9.5, 199.0, 199.5], atol=1e-12)
    np.testing.assert_allclose(observation[1:7, 2].numpy() * 24.0, [4.0, -4.0, 4.0, -4.0, 8.0, 0.0], atol=1e-12)
    assert observation[7].tolist() == [0.0] * 5
    np.testing.assert_array_equal(observation.numpy(), highway_env_observations(highway_envs[6], state, 0, 8)[1])


@pytest.mark.parametrize("rows", (1,) + ROW_COUNTS)
@pytest.mark.parametrize("lanes", LANE_COUNTS)
def test_the_highway_env_worlds_numpy_kinematics_are_highway_env_s_to_the_bit(highway_envs, lanes, rows):
    """mmpc.highway's own Kinematics (no pandas) on the random scenes: highway-env's float32 values exactly."""
    generator = torch.Generator().manual_seed(1000 + 100 * lanes + rows)
    for environments, slots in SCENE_BATCHES:
        state = random_scenes(lanes, environments, slots, generator)
        for environment in range(environments):
            expected = highway_env_observations(highway_envs[lanes], state, environment, rows)[0]
            ours = DeferredKinematics(highway_envs[lanes].unwrapped, rows)
            assert ours.observe().shape == (rows, 5) and not ours.observe().any()  # highway-env's per-frame call: a placeholder
            observation = ours.compute()
            assert observation.dtype == np.float32 and observation.shape == expected.shape
            np.testing.assert_array_equal(observation, expected)


def test_a_highway_env_episode_observes_only_when_asked_and_as_highway_env_does():
    """Along real traffic: highway-env's own observation at every frame is the placeholder, the
    episode's Kinematics rows are highway-env's (5 by default, any count asked for)."""
    episode = HighwayEpisode(load_scenario("cruise"), 7)
    assert isinstance(episode.unwrapped.observation_type, DeferredKinematics)
    for step in range(10):
        episode.apply(0.5 * np.sin(step), 0.01 * np.cos(step))
        for rows, asked in [(5, None), (7, 7), (7, None), (5, 5)]:  # None: the rows last asked for (first: 5)
            np.testing.assert_array_equal(episode.kinematics(asked),
                                          KinematicObservation(episode.unwrapped, vehicles_count=rows).observe())
        assert episode.observe().kinematics.shape == (1, 5, 5)
    episode.close()


def test_float32_states_are_observed_in_float64(highway_envs):
    """float32 positions whose float32 difference rounds up to 200 m: 199.999997 m apart, seen."""
    state = vehicle_state(torch.tensor([[-0.3, 199.7]]), torch.tensor([[4.0, 4.0]]), speed=20.0, config=SimConfig(lanes=3))
    assert float(state.x[0, 1] - state.x[0, 0]) == 200.0 and float(state.x[0, 1].double() - state.x[0, 0].double()) < 200.0
    observation = kinematics_observation(state, SimConfig(lanes=3), vehicles_count=3)
    assert observation[0, :, 0].tolist() == [1.0, 1.0, 0.0]
    np.testing.assert_array_equal(observation[0].numpy(), highway_env_observations(highway_envs[3], state, 0, 3)[0])


def test_one_row_is_the_ego_s(highway_envs):
    """highway-env's ``count=0`` means "no limit": with one row it returns every perceived vehicle too."""
    state = random_scenes(4, 1, 12, torch.Generator().manual_seed(3))
    ours = kinematics_observation(state, SimConfig(lanes=4), vehicles_count=1)
    theirs = highway_env_observations(highway_envs[4], state, 0, 1)[1]
    assert ours.shape == (1, 1, 5) and theirs.shape[0] > 1
    np.testing.assert_allclose(ours[0].numpy(), theirs[:1], rtol=0, atol=FLOAT64_TOLERANCE)


def test_the_project_s_environments_observe_with_the_defaults(highway_envs):
    observation_type = highway_envs[3].unwrapped.observation_type
    assert type(observation_type) is KinematicObservation
    assert (observation_type.features, observation_type.vehicles_count) == (list(FEATURES), 5)
    assert (observation_type.absolute, observation_type.order, observation_type.see_behind) == (False, "sorted", False)
    assert observation_type.normalize and observation_type.clip and not observation_type.observe_intentions


def _state_of(episode: HighwayEpisode, lanes: int) -> VehicleState:
    vehicles = episode.unwrapped.road.vehicles
    assert vehicles[0] is episode.ego

    def row(values):
        return torch.tensor([values], dtype=torch.float64)

    return vehicle_state(row([v.position[0] for v in vehicles]), row([v.position[1] for v in vehicles]),
                         heading=row([v.heading for v in vehicles]), speed=row([v.speed for v in vehicles]),
                         length=row([v.LENGTH for v in vehicles]), config=SimConfig(lanes=lanes))


@pytest.mark.parametrize("lanes, count, rows", [(3, 30, 5), (6, 18, 7)])
def test_observation_along_an_episode_of_idm_traffic(lanes, count, rows):
    """highway-env's own traffic without the window (vehicles behind and beyond 200 m), 12 steps."""
    scenario = dataclasses.replace(load_scenario("cruise"), lanes=lanes, traffic=IDMTraffic(vehicles_count=count, window=None))
    episode = HighwayEpisode(scenario, 0)
    reference = Float64Kinematics(episode.unwrapped, vehicles_count=rows)
    for step in range(12):
        episode.apply(0.5 * np.sin(step), 0.01 * np.cos(step))
        ours = kinematics_observation(_state_of(episode, lanes), SimConfig(lanes=lanes), vehicles_count=rows)
        np.testing.assert_allclose(ours[0].numpy(), reference.observe(), rtol=0, atol=FLOAT64_TOLERANCE)
    episode.close()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_no_environments_give_an_empty_batch(dtype):
    state = vehicle_state(torch.zeros(0, 3, dtype=dtype), torch.zeros(0, 3, dtype=dtype))
    observation = kinematics_observation(state, SimConfig(), vehicles_count=5)
    assert observation.shape == (0, 5, 5) and observation.dtype == dtype


@pytest.mark.parametrize("count", [0, -1, 2.5, True, "5", None])
def test_bad_vehicles_count_is_refused(count):
    state = vehicle_state(torch.zeros(1, 2), torch.zeros(1, 2))
    with pytest.raises(ValueError, match="`vehicles_count` must be an int >= 1"):
        kinematics_observation(state, SimConfig(), vehicles_count=count)


def _dead_ego(state: VehicleState) -> VehicleState:
    return state._replace(alive=torch.zeros_like(state.alive))


@pytest.mark.parametrize("spoil, config, match", [
    (tuple, SimConfig(), "`state` must be a VehicleState"),
    (lambda state: state._replace(y=state.y[:, :1]), SimConfig(), r"`state.y` must have shape \(1, 2\)"),
    (lambda state: state._replace(x=state.x.half()), SimConfig(), "`state.x` must be float32 or float64"),
    (lambda state: state._replace(speed=torch.full_like(state.speed, torch.nan)), SimConfig(), "`state.speed` holds NaN"),
    (lambda state: state, SimConfig(lanes=2), r"`state.lane` must lie in \[0, 1\]"),
    (lambda state: state, {"lanes": 4}, "`config` must be a SimConfig"),
    (_dead_ego, SimConfig(), r"`state.alive\[:, 0\]` must be True"),
], ids=["not-a-state", "shape", "dtype", "nan", "lane-beyond-road", "config", "dead-ego"])
def test_bad_state_or_config_is_refused(spoil, config, match):
    state = vehicle_state(torch.zeros(1, 2), torch.tensor([[12.0, 0.0]]), config=SimConfig(lanes=4))
    with pytest.raises(ValueError, match=match):
        kinematics_observation(spoil(state), config)
