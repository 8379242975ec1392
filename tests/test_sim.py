"""mmpc.sim against the real highway-env: same scenes stepped in both, the collision test on
random rectangle pairs, determinism, dtypes and devices, refused input.

highway-env is imported here only (the simulator itself does not import it)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from mmpc.sim import HighwaySimulator, SimConfig, VehicleState, pair_collisions, vehicle_state

highway_env = pytest.importorskip("highway_env")
from highway_env.vehicle.behavior import IDMVehicle  # noqa: E402
from highway_env.vehicle.kinematics import Vehicle  # noqa: E402

from mmpc.highway.episode import HighwayEpisode  # noqa: E402
from mmpc.scenario import EgoConfig, ScenarioConfig  # noqa: E402
from mmpc.traffic_config import ScriptedTraffic  # noqa: E402

LANES = 3
#: Rows (x [m], y [m], heading [rad], speed [m/s], target speed [m/s], IDM delta); row 0 the ego.
FOLLOWING = (  # one lane of IDM traffic around the ego: following, a target above the limit, lateral offsets
    (50.0, 4.0, 0.0, 14.0, 14.0, 4.0),
    (90.0, 4.0, 0.0, 18.0, 22.0, 4.0),
    (130.0, 4.3, 0.01, 15.0, 16.0, 3.7),
    (10.0, 4.0, 0.0, 24.0, 35.0, 4.4),
    (-30.0, 3.6, -0.02, 25.0, 28.0, 3.5),
    (160.0, 4.0, 0.0, 10.0, 12.0, 4.2),
)
CRASH = (  # the ego rams a slow car; the car behind and one beside join the pile-up
    (50.0, 4.0, 0.0, 25.0, 25.0, 4.0),
    (80.0, 4.0, 0.0, 3.0, 3.0, 4.0),
    (20.0, 4.0, 0.0, 25.0, 28.0, 4.0),
    (62.0, 7.9, 0.0, 24.0, 24.0, 4.0),
)
SCENES = {"following": FOLLOWING, "crash": CRASH}
DURATION = 20.0  # [s]
#: float32 tolerances over 20 s (measured at worst: 1.8e-3 m and 1.5e-4 m/s, 15 Hz following scene).
FLOAT32_POSITION_TOLERANCE, FLOAT32_SPEED_TOLERANCE = 1e-2, 1e-3


def ego_commands(scene: str, frequency: float) -> np.ndarray:
    """(N, 2) acceleration [m/s^2], steering [rad] for 20 s: a weave and, at the end, braking
    beyond the range to rest (the crash scene: full throttle)."""
    t = np.arange(int(DURATION * frequency)) / frequency
    if scene == "crash":
        return np.stack([np.full_like(t, 6.0), 0.003 * np.sin(t)], axis=1)
    return np.stack([np.sin(0.4 * t) - 0.6 - 8.0 * (t > 17.0), 0.004 * np.cos(0.7 * t)], axis=1)


def highway_env_run(rows, commands: np.ndarray, frequency: float, *, lane_changes: bool = False,
                    politeness: float = 0.0) -> np.ndarray:
    """(N, V, 5) x, y, speed, crashed, target lane of every vehicle after each command, in
    highway-env driven through the project's own path (HighwayEpisode.apply). Without
    ``lane_changes`` the IDM vehicles keep lane 1; with them, they start on their own lane with
    MOBIL on, the timer of row column 6 and ``politeness``."""
    scenario = ScenarioConfig(name="sim", lanes=LANES, frequency=frequency, duration=100.0,
                              traffic=ScriptedTraffic(), ego=EgoConfig(lane=1))
    episode = HighwayEpisode(scenario, seed=0)
    road = episode.unwrapped.road
    x, y, heading, speed = rows[0][:4]
    episode.ego.position, episode.ego.heading, episode.ego.speed = np.array([x, y]), heading, speed
    episode.ego.on_state_update()
    for x, y, heading, speed, target_speed, delta, *timer in rows[1:]:
        vehicle = IDMVehicle(road, [x, y], heading, speed, target_lane_index=None if lane_changes else ("0", "1", 1),
                             target_speed=target_speed, enable_lane_change=lane_changes)
        vehicle.DELTA, vehicle.POLITENESS = delta, politeness
        if lane_changes:
            vehicle.timer = timer[0]  # the constructor would replace 0 by its position-based value
        road.vehicles.append(vehicle)
    trace = []
    for acceleration, steering in commands:
        episode.apply(float(acceleration), float(steering))
        trace.append([[v.position[0], v.position[1], v.speed, v.crashed, getattr(v, "target_lane_index", v.lane_index)[2]]
                      for v in road.vehicles])
    episode.close()
    return np.asarray(trace, dtype=np.float64)


def initial_state(rows, config: SimConfig, dtype: torch.dtype, device="cpu", *, lane_changes: bool = False) -> VehicleState:
    table = torch.tensor([rows], dtype=dtype, device=device)
    if lane_changes:
        return vehicle_state(table[..., 0], table[..., 1], table[..., 2], table[..., 3], config=config,
                             target_speed=table[..., 4], idm_delta=table[..., 5],
                             lane_change_timer=torch.tensor([rows], dtype=torch.float64, device=device)[..., 6])
    return vehicle_state(table[..., 0], table[..., 1], table[..., 2], table[..., 3], config=config,
                         target_speed=table[..., 4], idm_delta=table[..., 5],
                         target_lane=torch.ones(table.shape[:2], dtype=torch.int64, device=device),
                         lane_change_enabled=False)


def sim_run(rows, commands: np.ndarray, frequency: float, dtype: torch.dtype, *, lane_changes: bool = False,
            politeness: float = 0.0) -> np.ndarray:
    """The same trace as :func:`highway_env_run`, from mmpc.sim."""
    config = SimConfig(simulation_frequency=frequency, policy_frequency=frequency, lanes=LANES, politeness=politeness)
    simulator = HighwaySimulator(config)
    state = initial_state(rows, config, dtype, lane_changes=lane_changes)
    trace = []
    for command in torch.tensor(commands, dtype=dtype)[:, None]:
        state = simulator.step(state, command)
        trace.append(torch.stack([state.x[0], state.y[0], state.speed[0], state.crashed[0].to(dtype),
                                  state.target_lane[0].to(dtype)], dim=1))
    return torch.stack(trace).double().numpy()


@pytest.mark.parametrize("frequency", [10.0, 15.0], ids=["10Hz", "15Hz-highway-env-default"])
@pytest.mark.parametrize("scene", sorted(SCENES))
def test_matches_highway_env_for_20_seconds(scene, frequency):
    commands = ego_commands(scene, frequency)
    expected = highway_env_run(SCENES[scene], commands, frequency)
    if scene == "crash":
        assert expected[-1, :, 3].all(), "the crash scene should crash every vehicle in highway-env"
    else:
        assert not expected[..., 3].any() and expected[-1, 0, 2] < 1.0  # no crash; the ego braked to (near) rest
    exact = sim_run(SCENES[scene], commands, frequency, torch.float64)
    # float64 measured at worst over every frame: 1.4e-14 m, 1.8e-15 m/s (the following scene: bit-identical positions)
    np.testing.assert_allclose(exact[..., :2], expected[..., :2], rtol=0, atol=1e-6)
    np.testing.assert_allclose(exact[..., 2], expected[..., 2], rtol=0, atol=1e-6)
    np.testing.assert_array_equal(exact[..., 3], expected[..., 3])
    single = sim_run(SCENES[scene], commands, frequency, torch.float32)
    np.testing.assert_allclose(single[..., :2], expected[..., :2], rtol=0, atol=FLOAT32_POSITION_TOLERANCE)
    np.testing.assert_allclose(single[..., 2], expected[..., 2], rtol=0, atol=FLOAT32_SPEED_TOLERANCE)
    np.testing.assert_array_equal(single[..., 3], expected[..., 3])


#: Rows (x [m], y [m], heading [rad], speed [m/s], target speed [m/s], IDM delta, lane-change timer [s]);
#: row 0 the ego (timer unused), driven straight at constant speed; lanes 0, 1, 2 at y = 0, 4, 8 m.
OVERTAKE = (  # a fast car behind a slow one, both neighbour lanes free: MOBIL accepts both, the right one wins
    (300.0, 0.0, 0.0, 25.0, 25.0, 4.0, 0.0),
    (60.0, 4.0, 0.0, 15.0, 15.0, 4.0, 0.3),
    (30.0, 4.0, 0.0, 25.0, 30.0, 4.0, 0.55),
)
UNSAFE = OVERTAKE + (  # cars close behind on both sides: the new follower would brake too hard until they pass
    (22.0, 0.0, 0.0, 25.0, 25.0, 4.0, 0.1),
    (24.0, 8.0, 0.0, 25.0, 25.0, 4.0, 0.7),
)
ABORT = (  # two fast cars change into the free middle lane in the same frame; the one behind aborts
    (400.0, 4.0, 0.0, 28.0, 28.0, 4.0, 0.0),
    (70.0, 0.0, 0.0, 15.0, 15.0, 4.0, 0.2),
    (40.0, 0.0, 0.0, 25.0, 30.0, 4.0, 0.95),
    (80.0, 8.0, 0.0, 15.0, 15.0, 4.0, 0.4),
    (50.0, 8.0, 0.0, 25.0, 30.0, 4.0, 0.95),
)
POLITE = (  # a small gain for car 2 against the braking it imposes on car 3 in the right lane; the ego behind on the left
    (100.0, 0.0, 0.0, 22.0, 22.0, 4.0, 0.0),
    (190.0, 4.0, 0.0, 21.5, 21.5, 4.0, 0.3),
    (130.0, 4.0, 0.0, 22.0, 22.0, 4.0, 0.95),
    (54.0, 8.0, 0.0, 25.0, 25.0, 4.0, 0.6),
)
#: scene id: (rows, politeness, every target-lane change as (step, slot, new lane), steps counted from 1).
LANE_CHANGE_SCENES = {
    "overtake-right-wins": (OVERTAKE, 0.0, [(6, 2, 2)]),
    "unsafe-until-passed": (UNSAFE, 0.0, [(28, 2, 2), (127, 2, 1), (130, 1, 0)]),
    "abort-same-target": (ABORT, 0.0, [(2, 2, 1), (2, 4, 1), (3, 2, 0), (24, 2, 1), (101, 2, 0), (109, 1, 1)]),
    "selfish": (POLITE, 0.0, [(2, 2, 2), (17, 3, 1)]),
    "polite": (POLITE, 1.0, [(9, 1, 2)]),  # car 2 stays; the slow car 1 moves over for it
}


def lane_changes_of(trace: np.ndarray, initial_lanes) -> list[tuple[int, int, int]]:
    """Every change of a target lane in ``trace`` (N, V, 5) as (step from 1, slot, new lane)."""
    lanes = np.concatenate([np.asarray(initial_lanes, dtype=np.float64)[None], trace[..., 4]])
    steps, slots = np.nonzero(np.diff(lanes, axis=0))
    return sorted((int(step) + 1, int(slot), int(lanes[step + 1, slot])) for step, slot in zip(steps, slots))


@pytest.mark.parametrize("scene", list(LANE_CHANGE_SCENES))
def test_lane_changes_match_highway_env_for_20_seconds(scene):
    rows, politeness, changes = LANE_CHANGE_SCENES[scene]
    frequency = 10.0
    commands = np.zeros((int(DURATION * frequency), 2))
    expected = highway_env_run(rows, commands, frequency, lane_changes=True, politeness=politeness)
    initial_lanes = [round(row[1] / 4.0) for row in rows]
    assert lane_changes_of(expected, initial_lanes) == changes  # the scene does what it is named for
    assert not expected[..., 3].any()
    exact = sim_run(rows, commands, frequency, torch.float64, lane_changes=True, politeness=politeness)
    assert lane_changes_of(exact, initial_lanes) == changes
    # float64 measured at worst over every frame: 2.5e-15 m, 3.6e-15 m/s (the abort scene)
    np.testing.assert_allclose(exact[..., :3], expected[..., :3], rtol=0, atol=1e-6)
    np.testing.assert_array_equal(exact[..., 3:], expected[..., 3:])
    single = sim_run(rows, commands, frequency, torch.float32, lane_changes=True, politeness=politeness)
    assert lane_changes_of(single, initial_lanes) == changes  # the float64 timers keep the decision frames
    np.testing.assert_allclose(single[..., :2], expected[..., :2], rtol=0, atol=FLOAT32_POSITION_TOLERANCE)
    np.testing.assert_allclose(single[..., 2], expected[..., 2], rtol=0, atol=FLOAT32_SPEED_TOLERANCE)


def test_default_lane_change_timer_is_highway_env_s():
    scenario = ScenarioConfig(name="sim", lanes=LANES, frequency=10.0, duration=10.0, traffic=ScriptedTraffic(),
                              ego=EgoConfig(lane=1))
    episode = HighwayEpisode(scenario, seed=0)
    positions = [(0.0, 0.0), (37.25, 4.0), (512.3, 8.1), (1e-3, 3.9)]
    expected = [IDMVehicle(episode.unwrapped.road, list(position)).timer for position in positions]
    episode.close()
    table = torch.tensor([positions], dtype=torch.float64)
    state = vehicle_state(table[..., 0], table[..., 1], config=SimConfig(lanes=LANES))
    np.testing.assert_array_equal(state.lane_change_timer[0].numpy(), expected)


def random_rectangle_pairs(count: int, seed: int = 0) -> np.ndarray:
    """(count, 2, 6) x [m], y [m], heading [rad], speed [m/s], length [m], width [m] of rectangle
    pairs (the first at the origin), about half intersecting: a third axis-aligned, nose to
    tail or side by side, 1 um to 1 mm from touching either way; the rest at random headings
    and centre distances."""
    rng = np.random.default_rng(seed)
    size = np.stack([rng.uniform(3.0, 8.0, (count, 2)), rng.uniform(1.5, 3.0, (count, 2))], axis=-1)
    heading = rng.uniform(-math.pi, math.pi, (count, 2))
    speed = rng.uniform(0.0, 30.0, (count, 2))
    reach = np.hypot(size[..., 0], size[..., 1]).sum(axis=1) / 2
    direction = rng.uniform(-math.pi, math.pi, count)
    distance = reach * rng.uniform(0.0, 1.0, count) ** 0.5
    centre = np.stack([distance * np.cos(direction), distance * np.sin(direction)], axis=-1)
    aligned = np.arange(count) % 3 == 0
    gap = rng.choice([-1.0, 1.0], count) * 10 ** rng.uniform(-6, -3, count)
    nose_to_tail = np.stack([(size[:, 0, 0] + size[:, 1, 0]) / 2 + gap, rng.uniform(-1.0, 1.0, count)], axis=-1)
    side_by_side = np.stack([rng.uniform(-2.0, 2.0, count), (size[:, 0, 1] + size[:, 1, 1]) / 2 + gap], axis=-1)
    touching = np.where(rng.integers(0, 2, count)[:, None] == 0, nose_to_tail, side_by_side)
    centre[aligned] = touching[aligned]
    heading[aligned] = 0.0
    positions = np.stack([np.zeros((count, 2)), centre], axis=1)
    return np.concatenate([positions, heading[..., None], speed[..., None], size], axis=-1)


def highway_env_collision(pair: np.ndarray, dt: float) -> tuple[bool, bool, np.ndarray]:
    """highway-env's own check of a pair: the first vehicle's ``_is_colliding`` with the second."""
    vehicles = []
    for x, y, heading, speed, length, width in pair:
        vehicle = Vehicle(None, [x, y], heading, speed)
        vehicle.LENGTH, vehicle.WIDTH, vehicle.diagonal = length, width, math.hypot(length, width)
        vehicles.append(vehicle)
    intersecting, will_intersect, translation = vehicles[0]._is_colliding(vehicles[1], dt)
    return bool(intersecting), bool(will_intersect), np.zeros(2) if translation is None else np.asarray(translation)


def test_collision_check_agrees_with_highway_env_on_random_pairs():
    dt, count = 0.1, 10_000
    pairs = random_rectangle_pairs(count)
    expected = [highway_env_collision(pair, dt) for pair in pairs]
    table = torch.tensor(pairs, dtype=torch.float64)
    state = vehicle_state(table[..., 0], table[..., 1], table[..., 2], table[..., 3], length=table[..., 4],
                          width=table[..., 5], config=SimConfig(lanes=1))
    result, untested = pair_collisions(state, dt)
    assert not untested.any()
    intersecting = np.array([e[0] for e in expected])
    will_intersect = np.array([e[1] for e in expected])
    assert 0.35 < intersecting.mean() < 0.65, intersecting.mean()  # about half intersect
    # measured: 10000 / 10000 agree on both flags (float32 too), translations within 2.2e-15 m
    np.testing.assert_array_equal(result.intersecting[:, 0, 1].numpy(), intersecting)
    np.testing.assert_array_equal(result.will_intersect[:, 0, 1].numpy(), will_intersect)
    np.testing.assert_allclose(result.translation[:, 0, 1].numpy(), np.array([e[2] for e in expected]), rtol=0, atol=1e-9)
    assert not result.intersecting[:, 1, 0].any() and not result.intersecting[:, 0, 0].any()  # pairs i < j only


def random_traffic(num_envs: int, dtype: torch.dtype, device="cpu", seed: int = 0) -> tuple[VehicleState, torch.Tensor]:
    """Dense random traffic on 3 lanes (crashes happen) with padding slots, and (50, E, 2) commands."""
    generator = torch.Generator().manual_seed(seed)
    shape = (num_envs, 8)
    x = torch.rand(shape, generator=generator, dtype=torch.float64) * 150
    y = torch.randint(0, LANES, shape, generator=generator).double() * 4 + torch.randn(shape, generator=generator, dtype=torch.float64) * 0.3
    speed = 10 + torch.rand(shape, generator=generator, dtype=torch.float64) * 15
    alive = torch.rand(shape, generator=generator) < 0.8
    alive[:, 0] = True
    commands = torch.randn((50, num_envs, 2), generator=generator, dtype=torch.float64) * torch.tensor([3.0, 0.05], dtype=torch.float64)
    state = vehicle_state(x.to(dtype).to(device), y.to(dtype).to(device), 0.0, speed.to(dtype).to(device),
                          config=SimConfig(lanes=LANES), alive=alive.to(device),
                          target_speed=(speed + 5 * torch.rand(shape, generator=generator, dtype=torch.float64)).to(dtype).to(device))
    return state, commands.to(dtype).to(device)


def run_commands(state: VehicleState, commands: torch.Tensor) -> VehicleState:
    simulator = HighwaySimulator(SimConfig(lanes=LANES))
    for command in commands:
        state = simulator.step(state, command)
    return state


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_deterministic_and_preserves_shapes_and_dtypes(dtype):
    state, commands = random_traffic(64, dtype)
    first, second = run_commands(state, commands), run_commands(state, commands)
    for name, a, b in zip(VehicleState._fields, first, second):
        assert torch.equal(a, b), name
        assert a.shape == getattr(state, name).shape and a.dtype == getattr(state, name).dtype, name
    assert first.crashed.any() and not first.crashed.all()  # the scene exercises collisions
    assert (first.target_lane != state.target_lane).any()  # and lane changes
    padding = ~state.alive
    assert torch.equal(first.x[padding], state.x[padding]) and not first.crashed[padding].any()


def test_environments_are_independent():
    state, commands = random_traffic(6, torch.float64)
    together = run_commands(state, commands)
    for e in range(6):
        alone = run_commands(VehicleState(*(field[e:e + 1] for field in state)), commands[:, e:e + 1])
        for name, a, b in zip(VehicleState._fields, together, alone):
            torch.testing.assert_close(a[e:e + 1], b, rtol=0, atol=1e-12, msg=name)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu():
    state, commands = random_traffic(256, torch.float64)
    expected = run_commands(state, commands)
    result = run_commands(VehicleState(*(field.cuda() for field in state)), commands.cuda())
    for name, a, b in zip(VehicleState._fields, result, expected):
        assert a.device.type == "cuda", name
        torch.testing.assert_close(a.cpu(), b, rtol=0, atol=1e-9, msg=name)


@pytest.mark.parametrize("command,message", [
    (torch.zeros(4, 3), r"`command` must have shape \(E, 2\).*got \(4, 3\)"),
    (torch.zeros(3, 2), r"`command` has 3 environments; the state has E = 4"),
    (torch.tensor([[0.0, 0.0], [math.nan, 0.0], [0.0, 0.0], [0.0, 0.0]]), r"`command` must be finite; NaN or inf in environments \[1\]"),
    (torch.zeros(4, 2, dtype=torch.int64), r"`command` must be a floating-point tensor"),
])
def test_bad_command_is_refused(command, message):
    state, _ = random_traffic(4, torch.float64)
    with pytest.raises(ValueError, match=message):
        HighwaySimulator(SimConfig(lanes=LANES)).step(state, command)


def test_bad_state_is_refused():
    config = SimConfig(lanes=LANES)
    state, commands = random_traffic(4, torch.float64)
    simulator = HighwaySimulator(config)
    with pytest.raises(ValueError, match=r"`state.y` must have shape \(4, 8\) like `state.x`; got \(3, 8\)"):
        simulator.step(state._replace(y=state.y[:3]), commands[0])
    with pytest.raises(ValueError, match=r"`state.speed` holds NaN or inf"):
        simulator.step(state._replace(speed=state.speed.clone().fill_(math.nan)), commands[0])
    with pytest.raises(ValueError, match=r"`state.heading` must be torch.float64; got torch.float32"):
        simulator.step(state._replace(heading=state.heading.float()), commands[0])
    with pytest.raises(ValueError, match=r"`state.target_lane` must lie in \[0, 2\]"):
        simulator.step(state._replace(target_lane=state.target_lane + 5), commands[0])
    with pytest.raises(ValueError, match=r"`x` must be a floating-point tensor of shape \(E, V\); got \(3,\)"):
        vehicle_state(torch.zeros(3), torch.zeros(3))
    with pytest.raises(ValueError, match=r"`speed` must broadcast to \(E, V\) = \(2, 3\); got \(2, 2\)"):
        vehicle_state(torch.zeros(2, 3), torch.zeros(2, 3), speed=torch.zeros(2, 2))
    with pytest.raises(ValueError, match=r"SimConfig: `simulation_frequency` \(5.0 Hz\) must be >= `policy_frequency`"):
        SimConfig(simulation_frequency=5.0, policy_frequency=10.0)
