"""Legal safety at every setting a scenario accepts: the frequencies, car sizes, lane counts and
speeds the loader takes are either covered by the check (no collision with a car that kept its
set, in adversarial traffic) or refused with the reason."""

import math

import pytest
import torch

import mmpc
from mmpc.config import ConfigError
from mmpc.drivers.base import Decision, Driver, Observation
from mmpc.drivers.verified import VerifiedDriver
from mmpc.highway.runner import run_lockstep
from mmpc.scenario import load_scenario
from mmpc.sim import HighwaySimulator, SimConfig, SimEpisodes, vehicle_state
from mmpc.sim.traffic import sim_config
from mmpc.traffic_config import THREATS_MIN_FREQUENCY
from mmpc.verify import TrafficAssumptions, Verifier


class RandomCommands(Driver):
    """Uniform accelerations in the ego's range and steering within +-0.1 rad, looking at nobody."""

    name = "random-commands"

    def __init__(self, seed: int = 0) -> None:
        self.generator = torch.Generator().manual_seed(seed)

    def decide(self, observation: Observation) -> Decision:
        count = observation.ego.shape[0]
        acceleration = torch.rand(count, generator=self.generator) * 10.0 - 5.0
        steering = (torch.rand(count, generator=self.generator) * 2.0 - 1.0) * 0.1
        return Decision.command_only(acceleration, steering, 0.0)


def test_the_lowest_frequency_is_the_lane_keeping_controllers_gain():
    assert THREATS_MIN_FREQUENCY == SimConfig().kp_heading  # 1 / kp_heading: the longest frame without overshoot


def test_the_check_refuses_frequencies_at_which_the_traffic_leaves_its_assumptions():
    for frequency in (1.0, 2.0, 4.0):
        with pytest.raises(ValueError, match=f"simulation frequency >= 5 Hz.*got {frequency:g} Hz"):
            Verifier.for_scenario(load_scenario("high_speed", {"frequency": frequency}))
        with pytest.raises(ConfigError, match="threatening traffic keeps its cars within the verification's assumptions"):
            load_scenario("high_speed_threats", {"frequency": frequency})
    with pytest.raises(ValueError, match="one simulation frame per command"):
        Verifier(mmpc.Road(num_lanes=4), SimConfig(simulation_frequency=20.0, policy_frequency=10.0))
    with pytest.raises(ValueError, match="`margin` must cover the one-frame sweep"):
        Verifier(mmpc.Road(num_lanes=4), SimConfig(simulation_frequency=5.0, policy_frequency=5.0), margin=0.05)
    Verifier.for_scenario(load_scenario("high_speed", {"frequency": 5.0}))  # the lowest covered


@pytest.mark.parametrize("frequency", [2.0, 5.0, 15.0])
def test_the_traffic_keeps_the_assumed_heading_only_at_the_covered_frequencies(frequency):
    """Why the floor: with frames longer than 1 / kp_heading the lane-keeping controller overshoots
    and the cars turn past the heading (and lateral speed) the sets assume; at and above it they never do."""
    scenario = load_scenario("high_speed", {"sim": "batched", "frequency": frequency, "duration": 20.0})
    episodes = SimEpisodes(scenario, seeds=list(range(32)))
    assumptions, largest = TrafficAssumptions(), 0.0
    for _ in range(int(20 * frequency)):
        state = episodes.state
        present = state.alive[:, 1:] & ~state.crashed[:, 1:]
        largest = max(largest, float(state.heading[:, 1:].abs()[present].max()))
        episodes.step(torch.zeros(32, 2))
    if frequency < THREATS_MIN_FREQUENCY:
        assert largest > assumptions.max_heading
    else:
        assert largest <= assumptions.max_heading


def test_the_assumptions_follow_the_scenarios_cars():
    scenario = load_scenario("high_speed", {"vehicle_size": [6.0, 2.3], "optimizer": {"ellipse_a": 9.0, "ellipse_b": 4.5}})
    assumptions = Verifier.for_scenario(scenario).assumptions
    assert (assumptions.length, assumptions.width) == (6.0, 2.3)
    assert assumptions.lane_overreach == pytest.approx(TrafficAssumptions().lane_overreach + 0.15)
    assert Verifier.for_scenario(load_scenario("high_speed")).assumptions == TrafficAssumptions()


def test_a_command_that_leaves_the_road_does_not_verify():
    verifier = Verifier(mmpc.Road(num_lanes=4))
    ego = mmpc.ego_state(0.0, -1.5, -0.4, 20.0).reshape(1, 6)  # lane 0, heading for the road's left edge (y = -2)
    empty, none = torch.zeros(1, 0, 4), torch.zeros(1, 0, dtype=torch.bool)
    verdict = verifier.check(ego, empty, none, torch.tensor([[0.0, 0.0]]), torch.tensor([[-0.5, 0.3]]))
    assert verdict.verified.tolist() == [[False, True]]


def test_the_check_counts_the_worlds_look_ahead_of_one_frame():
    """highway-env (and mmpc.sim) crashes two cars whose rectangles, swept one frame along their
    headings, meet. A scene found by sampling at 5 Hz: the ego, turned towards lane 0, passes a car
    braking to rest there; after the command its rectangle clears the car, its sweep does not, and
    the world crashes it at the next frame whatever it does. A check of the rectangle alone took it."""
    sim = SimConfig(simulation_frequency=5.0, policy_frequency=5.0)
    ego = torch.tensor([[0.0, 4.12, -0.39, 12.28, 0.0, 0.0]])
    cars = torch.tensor([[[16.7, 0.0, 0.2, 0.0], [8.6, 0.0, 1.7, 0.0], [31.7, 8.0, 5.3, 0.0]]])
    command = torch.tensor([[0.79, 0.04]])
    verdict = Verifier(mmpc.Road(num_lanes=4), sim).check(ego, cars, torch.ones(1, 3, dtype=torch.bool), command[:, :1],
                                                           command[:, 1:])
    assert verdict.verified.tolist() == [[False]]
    # the world: after the command the ego is marked to crash into car 2 (slot 2) at the next frame
    state = vehicle_state(torch.tensor([[0.0, 16.7, 8.6, 31.7]]), torch.tensor([[4.12, 0.0, 0.0, 8.0]]),
                          heading=torch.tensor([[-0.39, 0.0, 0.0, 0.0]]), speed=torch.tensor([[12.28, 0.2, 1.7, 5.3]]),
                          config=sim, lane_change_enabled=False)
    state = HighwaySimulator(sim).step(state, command)
    assert not bool(state.crashed.any()) and state.impact_pending[0].tolist() == [True, False, True, False]
    assert bool(HighwaySimulator(sim).step(state, torch.tensor([[-5.0, 0.0]])).crashed[0, 0])


#: Settings the loader accepts, each swept in adversarial traffic (high_speed_threats): the
#: frequencies from the floor up, few and many lanes, smaller and larger cars, fast traffic, traffic
#: that reads the ego as an IDM follower.
SETTINGS = [
    {"frequency": 5.0},
    {"frequency": 15.0},
    {"frequency": 30.0, "duration": 3.0},
    {"lanes": 2},
    {"lanes": 3},
    {"vehicle_size": [4.0, 1.8]},
    {"vehicle_size": [6.0, 2.3], "optimizer": {"ellipse_a": 9.0, "ellipse_b": 4.5}},
    {"traffic": {"target_speeds": [20.0, 28.0]}, "ego": {"speed": 25.0}},
    {"traffic.ego_as_follower": True},  # cut-ins directly ahead of the ego where MOBIL allows them
]


@pytest.mark.parametrize("settings", SETTINGS, ids=lambda s: ",".join(f"{k}={v}" for k, v in s.items()))
def test_verified_random_commands_never_collide_with_a_car_that_kept_its_set(settings):
    """Random commands behind the check, 16 threatening episodes x 8 s per setting: a collision is
    allowed only with a car that left its set (the monitor says so) or in an episode that never had
    a verified way out (its start already had none: the induction has no base)."""
    scenario = load_scenario("high_speed_threats", {"sim": "batched", "duration": 8.0, **settings})
    driver = VerifiedDriver(RandomCommands(), Verifier.for_scenario(scenario))
    results = run_lockstep(scenario, list(range(16)), driver=driver)
    holes = [r.seed for r in results if r.metrics["collisions"] and not r.metrics["crash_collider_outside"]
             and r.metrics["first_verified_step"] is not None]
    assert holes == []
    assert sum(r.metrics["verified_share"] for r in results) / len(results) > 0.5  # the check lets the commands drive


def test_the_random_commands_are_a_threat_without_the_check():
    scenario = load_scenario("high_speed_threats", {"sim": "batched", "duration": 8.0})
    results = run_lockstep(scenario, list(range(16)), driver=RandomCommands())
    assert sum(r.metrics["collisions"] for r in results) >= 4


def test_a_verified_ego_turning_across_its_new_lane_is_not_struck_by_the_car_it_cut_in_front_of():
    """Found by the verified ceiling's beam search (high_speed, seed 78435, step 184): the ego, half a
    lane into lane 3 at 9.1 m/s, 0.5 m ahead of a car there at 8.1 m/s (which yields: the ego is
    faster), brakes at 5 m/s^2 while steering hard further across; its speed along the road falls
    faster than 5 m/s^2, the car behind cannot stop at 6 and strikes its side. Every command verified
    while a follower was left out of the check; its set now ends where its braking takes it."""
    scenario = load_scenario("high_speed", {"sim": "batched"})
    sim = sim_config(scenario)
    tensor = lambda values: torch.tensor([values], dtype=torch.float64)  # noqa: E731
    state = vehicle_state(tensor([427.922, 422.375, 425.627]), tensor([10.096, 12.0, 4.0]), heading=tensor([0.420, 0.0, 0.0]),
                          speed=tensor([9.095, 8.087, 10.337]), config=sim, target_speed=tensor([14.0, 9.47, 10.61]),
                          idm_delta=tensor([4.0, 3.54, 3.97]), lane_change_enabled=torch.tensor([[False, True, True]]),
                          lane_change_timer=tensor([19.01, 0.1, 0.0]))
    verifier, simulator = Verifier.for_scenario(scenario, compile=False), HighwaySimulator(sim)
    applied = (-5.0, -0.0731)
    for acceleration, steering in [(-5.0, -0.1749), (-5.0, 0.7854), (-5.0, 0.6813), (-5.0, 0.3880), (-5.0, 0.2123)]:
        slip = math.atan(0.5 * math.tan(applied[1]))
        speed = float(state.speed[0, 0])
        ego = tensor([float(state.x[0, 0]), float(state.y[0, 0]), float(state.heading[0, 0]) + slip, speed, applied[0],
                      speed * math.sin(slip) / 2.5])
        heading, others = state.heading[0, 1:], state.speed[0, 1:]
        cars = torch.stack([state.x[0, 1:], state.y[0, 1:], others * torch.cos(heading), others * torch.sin(heading)], dim=1)[None]
        verdict = verifier.check(ego, cars, torch.ones(1, 2, dtype=torch.bool), tensor([acceleration]), tensor([steering]))
        if not bool(verdict.verified[0, 0]):
            return  # the check refuses the manoeuvre: no hole
        state = simulator.step(state, tensor([acceleration, steering]))
        applied = (acceleration, steering)
        assert not bool(state.crashed[0, 0])
