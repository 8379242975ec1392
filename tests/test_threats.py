"""Threatening traffic (mmpc.sim.threats): the cars near the ego cut in, brake and overtake as hard
as the rules allow, stay inside the verification's assumptions, and are a real threat to a driver
that does not verify; a driver behind the check never collides with them."""

import dataclasses

import pytest
import torch

from mmpc.config import ConfigError
from mmpc.drivers.base import Decision, Driver, Observation
from mmpc.drivers.verified import VerifiedDriver
from mmpc.scenario import load_scenario
from mmpc.traffic_config import IDMTraffic, Threats
from mmpc.sim import SimConfig, SimEpisodes, vehicle_state
from mmpc.sim.idm import steering_to_lane
from mmpc.sim.threats import threaten_lanes, threaten_speeds
from mmpc.verify import AssumptionMonitor, Verifier

CONFIG = SimConfig(lanes=4)
SEED, STEP = torch.tensor([7]), torch.tensor([0])


def scene(cars, ego_heading=0.0, timer=0.0):
    """One environment: the ego at x = 0 on lane 1 (y = 4) at 20 m/s, then ``cars`` [(x, y, speed)]
    settled on their lanes, each with its MOBIL timer at ``timer`` (0: it decided this frame)."""
    x = torch.tensor([[0.0] + [car[0] for car in cars]])
    y = torch.tensor([[4.0] + [car[1] for car in cars]])
    speed = torch.tensor([[20.0] + [car[2] for car in cars]])
    heading = torch.tensor([[ego_heading] + [0.0] * len(cars)])
    timer = torch.full(x.shape, timer, dtype=torch.float64)
    return vehicle_state(x, y, heading, speed, config=CONFIG, lane_change_timer=timer)


def test_a_car_ahead_cuts_into_the_lane_the_ego_moves_into_but_not_in_front_of_the_ego():
    threats = Threats()
    # a car ahead on lane 3; the ego on lane 1 moving towards lane 2: the car turns to lane 2
    moving = threaten_lanes(scene([(30.0, 12.0, 15.0)], ego_heading=0.05), threats, SEED, STEP, CONFIG)
    assert moving.target_lane[0, 1] == 2 and moving.lane_change_timer[0, 1] == 0
    # the ego holding lane 1 with a car beside it ahead on lane 2: the ego would be its new follower, MOBIL refuses
    holding = threaten_lanes(scene([(30.0, 8.0, 15.0)]), threats, SEED, STEP, CONFIG)
    assert holding.target_lane[0, 1] == 2
    # ... unless a car is between them on the ego's lane: then it may enter ahead of that car
    between = threaten_lanes(scene([(55.0, 8.0, 15.0), (8.0, 4.0, 15.0)]), threats, SEED, STEP, CONFIG)
    assert between.target_lane[0, 1] == 1
    # a car that did not just decide (its MOBIL timer runs), or one behind the ego, does not turn
    waiting = threaten_lanes(scene([(30.0, 12.0, 15.0)], ego_heading=0.05, timer=0.5), threats, SEED, STEP, CONFIG)
    behind = threaten_lanes(scene([(-30.0, 12.0, 15.0)], ego_heading=0.05), threats, SEED, STEP, CONFIG)
    assert waiting.target_lane[0, 1] == 3 and behind.target_lane[0, 1] == 3


def test_cars_ahead_brake_as_hard_as_idm_may_and_cars_beside_behind_speed_up():
    state = scene([(30.0, 4.0, 15.0), (-20.0, 8.0, 15.0), (-20.0, 4.0, 15.0)])
    idm = torch.zeros(1, 4)
    always = Threats(brake_share=1.0)
    acceleration = threaten_speeds(state, idm, always, SEED, STEP, 10.0, CONFIG)
    assert acceleration[0, 1] == -CONFIG.acc_max  # the leader brakes
    assert acceleration[0, 2] == CONFIG.comfort_acc_max  # behind, beside the ego: overtakes
    assert acceleration[0, 3] == 0.0  # behind in the ego's lane: IDM (it answers for its own distance)
    assert acceleration[0, 0] == 0.0  # the ego's own command is not the traffic's
    never = threaten_speeds(state, idm, Threats(brake_share=0.0, overtake=False), SEED, STEP, 10.0, CONFIG)
    assert bool((never == 0.0).all())
    # near rest the braking stops the car, never reverses it
    slow = scene([(30.0, 4.0, 0.2)])
    assert float(threaten_speeds(slow, torch.zeros(1, 2), always, SEED, STEP, 10.0, CONFIG)[0, 1]) == pytest.approx(-2.0)


def test_the_threats_are_validated_and_run_on_the_batched_simulator_only():
    with pytest.raises(ValueError, match="brake_share"):
        Threats(brake_share=1.5)
    with pytest.raises(ValueError, match="reach"):
        Threats(reach=0.0)
    with pytest.raises(ConfigError, match="batched simulator only"):
        load_scenario("high_speed_threats", {"sim": "highway-env"})
    scenario = load_scenario("cruise_threats")
    assert scenario.sim == "batched" and scenario.duration == 10.0 and scenario.traffic.threats == Threats()
    assert dataclasses.replace(IDMTraffic()).threats is None  # naturalistic by default


class Reckless(Driver):
    """Asks for 3 m/s^2 always and changes between lanes 1 and 2 every 4 s, looking at nobody."""

    name = "reckless"
    steps = 0

    def decide(self, observation: Observation) -> Decision:
        ego = observation.ego
        target = torch.full_like(ego[:, 1], 4.0 * (1 + (self.steps // 40) % 2))
        self.steps += 1
        steering = steering_to_lane(ego[:, 1], ego[:, 2], ego[:, 3], 5.0, target, CONFIG, max_steering=0.1)
        return Decision.command_only(torch.full_like(ego[:, 0], 3.0), steering, 0.0)


def drive_in_threats(verified: bool, envs: int = 16) -> tuple[torch.Tensor, int, int]:
    """A reckless driver in threatening high-speed traffic, 16 episodes x 10 s: which collided, how
    many cars left their sets while the ego moved, and how many car-steps were watched."""
    scenario = load_scenario("high_speed_threats")
    episodes = SimEpisodes(scenario, seeds=list(range(500, 500 + envs)))
    driver = VerifiedDriver(Reckless(), Verifier.for_scenario(scenario)) if verified else Reckless()
    driver.reset(envs)
    monitor = AssumptionMonitor(scenario.road, scenario.period)
    ids = torch.arange(envs)
    collided = torch.zeros(envs, dtype=torch.bool)
    outside, watched = 0, 0
    for _ in range(int(scenario.duration * scenario.frequency)):
        ego, vehicles, mask = episodes.road_state()
        live = mask & ~episodes.state.crashed[:, 1:]
        moving = (ego[:, 3] > 0) & ~collided
        # IDM reverses a car stopped closer to its leader than it wants (a breach the assumptions name
        # and the monitor flags, :mod:`mmpc.verify.assumptions`): it moves away; any other breach counts
        reversing = vehicles[..., 2] < 0
        broke = monitor.observe(ids, ego, vehicles, live) & moving[:, None] & ~reversing
        outside += int(broke.sum())
        watched += int((live & moving[:, None]).sum())
        decision = driver.decide(Observation(ego, vehicles, mask, None, ids))
        episodes.step(torch.stack([decision.acceleration, decision.steering], dim=1).float(), running=~collided)
        collided |= episodes.crashed
    return collided, outside, watched


def test_threatening_traffic_keeps_the_assumptions_and_verified_driving_never_collides_with_it():
    collided, outside, watched = drive_in_threats(verified=True)
    assert not bool(collided.any())
    assert watched > 10000 and outside == 0  # while the ego moves, no car leaves the set the check assumed
    reckless, _, _ = drive_in_threats(verified=False)
    assert int(reckless.sum()) >= 4  # the traffic is a threat
