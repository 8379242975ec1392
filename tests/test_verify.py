"""Legal safety (mmpc.verify): the assumptions are the worlds' rules, the batched simulator's cars
keep them, the check refuses what can end in a collision, and verified driving never collides
with traffic that keeps them, however adversarial."""

import math

import pytest
import torch

import mmpc
from mmpc.drivers import make_driver
from mmpc.drivers.base import Decision, Driver, Observation
from mmpc.drivers.verified import VerifiedDriver
from mmpc.highway.runner import run_lockstep
from mmpc.road import Road
from mmpc.scenario import load_scenario
from mmpc.sim import SimConfig, SimEpisodes
from mmpc.verify import AssumptionMonitor, TrafficAssumptions, Verifier, counted_lanes, occupancy
from mmpc.verify.failsafe import Body, drive
from mmpc.verify.geometry import rectangle_meets_box
from mmpc.verify.monitor import outside
from mmpc.verify.occupancy import held_variant

ROAD = Road(num_lanes=4)


def check(ego, cars, acceleration=0.0, steering=0.0, **assumptions):
    """Whether one command of one ego verifies among ``cars`` [(x, y, vx, vy)]."""
    verifier = Verifier(ROAD, assumptions=TrafficAssumptions(**assumptions))
    vehicles = torch.tensor([cars], dtype=torch.float32).reshape(1, -1, 4)
    mask = torch.ones(vehicles.shape[:2], dtype=torch.bool)
    verdict = verifier.check(ego.reshape(1, 6), vehicles, mask, torch.tensor([[acceleration]]), torch.tensor([[steering]]))
    return bool(verdict.verified[0, 0])


def test_the_assumptions_are_the_worlds_rules():
    from highway_env.vehicle.behavior import IDMVehicle

    assumptions, sim = TrafficAssumptions(), SimConfig()
    assert assumptions.max_deceleration == sim.acc_max == IDMVehicle.ACC_MAX
    assert assumptions.max_acceleration == sim.comfort_acc_max == IDMVehicle.COMFORT_ACC_MAX
    assert assumptions.speed_limit == sim.speed_limit
    assert assumptions.lane_margin == sim.lane_margin
    assert assumptions.max_heading > math.pi / 4  # the controller's heading reference clip, with its overshoot
    # the cut-in rule's IDM and MOBIL constants, and the ego's command range
    assert assumptions.distance_wanted == sim.distance_wanted == IDMVehicle.DISTANCE_WANTED
    assert assumptions.time_wanted == sim.time_wanted == IDMVehicle.TIME_WANTED
    assert -assumptions.comfort_deceleration == sim.comfort_acc_min == IDMVehicle.COMFORT_ACC_MIN
    assert assumptions.max_braking_imposed == sim.lane_change_max_braking_imposed == IDMVehicle.LANE_CHANGE_MAX_BRAKING_IMPOSED
    assert assumptions.ego_acceleration == max(abs(bound) for bound in sim.acceleration_range)
    assert TrafficAssumptions.for_scenario(load_scenario("high_speed")) == assumptions
    with pytest.raises(ValueError, match="max_deceleration"):
        TrafficAssumptions(max_deceleration=0.0)


def _cars_stay_in_their_sets(name, overrides=None, random_ego=False):
    """16 episodes x 12 s of scenario ``name``: no car that stays near the ego leaves the set predicted
    for it one step (the monitor), five steps or one second ahead (decisions to cut in anywhere in
    that second counted as possible). The ego holds its speed, or (``random_ego``) draws a command in
    its whole range every step, and may run into cars: a crashed car (braking at -v per second,
    pushed) has left the assumptions and is not checked. Returns the car-steps checked."""
    scenario = load_scenario(name, {"sim": "batched", "duration": 12.0, **(overrides or {})})
    episodes = SimEpisodes(scenario, seeds=list(range(900, 916)))
    monitor = AssumptionMonitor(scenario.road, scenario.period)
    times = torch.arange(11) * scenario.period
    assumptions = TrafficAssumptions()
    generator = torch.Generator().manual_seed(5)
    history, checked = [], 0
    for step in range(int(12.0 * scenario.frequency)):
        ego, vehicles, mask = episodes.road_state()
        mask = mask & ~episodes.state.crashed[:, 1:]
        assert not bool(monitor.observe(torch.arange(16), ego, vehicles, mask).any()), (name, step)
        near = mask & ((vehicles[..., 0] - ego[:, None, 0]).abs() < 80.0)
        sets = occupancy(ego, vehicles, near, scenario.road, times, assumptions, fault_rule=False,
                         decided_within=float(times[-1]))
        for ago, (old_sets, old_near, old_x) in enumerate(reversed(history), start=1):
            if ago not in (5, 10):
                continue
            held = held_variant(old_sets.ego_lanes, ego[:, 1, None], scenario.road, assumptions.lane_margin)
            same = (vehicles[..., 0] - old_x).abs() < 45.0 * ago * scenario.period  # not moved by the window
            kept = old_near & same & mask  # crashed is for good: a car crashed since is not checked
            gone = outside(old_sets, ago - 1, vehicles, held, assumptions) & kept
            assert not bool(gone.any()), (name, step, ago)
            checked += int(kept.sum())
        history = (history + [(sets, near, vehicles[..., 0].clone())])[-10:]
        command = torch.zeros(16, 2)
        if random_ego:
            command[:, 0] = torch.rand(16, generator=generator) * 10.0 - 5.0
        episodes.step(command)
    return checked


def test_the_batched_simulators_cars_stay_in_their_sets():
    """Naturalistic traffic of both scenarios, the ego holding its speed."""
    for name in ("high_speed", "cruise"):
        assert _cars_stay_in_their_sets(name) > 5000


def test_cars_that_cut_in_ahead_of_an_ego_read_as_a_follower_stay_in_their_sets():
    """Threatening traffic whose MOBIL reads the ego as an IDM follower (cars cut in ahead of it where
    the follower rule lets them), the ego braking and speeding at random: the sets of the default rule
    (``cut_in="follower"``) hold every car."""
    overrides = {"traffic.ego_as_follower": True}
    assert _cars_stay_in_their_sets("high_speed_threats", overrides, random_ego=True) > 5000


def test_a_monitor_flags_a_car_that_brakes_harder_than_assumed():
    monitor = AssumptionMonitor(ROAD, 0.1)
    ego = mmpc.ego_state(0.0, 4.0, 0.0, 20.0).reshape(1, 6)
    before = torch.tensor([[[30.0, 4.0, 20.0, 0.0], [30.0, 8.0, 20.0, 0.0]]])
    assert monitor.observe(torch.tensor([0]), ego, before, None).tolist() == [[False, False]]
    # car 0 stops dead (a crashed car's -v per second), car 1 brakes at 5 m/s^2
    after = torch.tensor([[[31.0, 4.0, 0.0, 0.0], [31.975, 8.0, 19.5, 0.0]]])
    ego_after = mmpc.ego_state(2.0, 4.0, 0.0, 20.0).reshape(1, 6)
    assert monitor.observe(torch.tensor([0]), ego_after, after, None).tolist() == [[True, False]]
    # another environment's first observation: nothing to compare with
    assert monitor.observe(torch.tensor([1]), ego_after, after, None).tolist() == [[False, False]]


def test_the_check_keeps_the_stopping_distance_to_a_car_ahead():
    ego = mmpc.ego_state(0.0, 4.0, 0.0, 20.0)
    # The ego stops in 40 m at 5 m/s^2; the car ahead at 20 m/s in 33 m at 6 m/s^2.
    assert check(ego, [[40.0, 4.0, 20.0, 0.0]])
    assert not check(ego, [[12.0, 4.0, 20.0, 0.0]])
    assert not check(ego, [[45.0, 4.0, 0.0, 0.0]])  # stopped traffic within the stopping distance
    assert check(ego, [[80.0, 4.0, 0.0, 0.0]])
    # Speeding up towards it is refused where holding the speed is not.
    assert check(ego, [[21.0, 4.0, 20.0, 0.0]])
    assert not check(ego, [[21.0, 4.0, 20.0, 0.0]], acceleration=5.0)


def test_a_car_beside_may_not_cut_in_ahead_of_the_moving_ego_unless_it_is_changing_lane_already():
    ego = mmpc.ego_state(0.0, 4.0, 0.0, 20.0)
    beside = [5.0, 8.0, 20.0, 0.0]
    assert check(ego, [beside])  # MOBIL's criterion: it may enter only far enough ahead of the ego following it
    assert not check(ego, [beside], cut_in="any")
    assert not check(ego, [[5.0, 7.0, 20.0, -2.0]])  # decided before now: it comes
    assert check(ego, [[5.0, 9.0, 20.0, 2.0]])  # changing away


def test_a_car_behind_answers_for_its_own_distance_where_its_braking_keeps_it_behind():
    ego = mmpc.ego_state(0.0, 4.0, 0.0, 20.0)
    assert check(ego, [[-8.0, 8.0, 30.0, -2.0]])  # entering the ego's lane behind it: kept out of it
    # A follower in the ego's lane: one that stops behind the braking ego answers for its distance,
    # one that cannot stays in the check (its strike would find the ego's side wherever the ego turns).
    assert check(ego, [[-20.0, 4.0, 24.0, 0.0]])
    assert not check(ego, [[-8.0, 4.0, 30.0, 0.0]])
    # An ego that brakes harder along the road than straight braking (turning while braking) is refused
    # where straight braking passes: the follower's set follows the path, not a bound on the ego.
    close = [[-8.0, 4.0, 20.0, 0.0]]
    assert check(ego, close, acceleration=-5.0)
    assert not check(mmpc.ego_state(0.0, 4.0, 0.4, 20.0), close, acceleration=-5.0, steering=0.7)


def test_the_ego_may_not_cut_in_close_in_front_of_a_car_behind():
    """The scene the threatening traffic found (tests/test_threats.py, seed 503 before the fix): the
    ego, between lanes 2 and 3 and heading into lane 2, beside a car on lane 2 whose front is
    alongside the ego's rear. That car does not answer for a gap the ego closes from the side."""
    entering = mmpc.ego_state(0.0, 10.5, -0.2, 15.0)
    assert not check(entering, [[-3.0, 8.0, 10.0, 0.0]])  # alongside: the ego's to avoid
    assert not check(entering, [[-9.0, 8.0, 28.0, 0.0]])  # behind, but too fast to stop behind the ego
    assert not check(mmpc.ego_state(0.0, 9.5, -0.2, 15.0), [[-12.0, 8.0, 25.0, 0.0]])  # past halfway: no abort left
    assert check(entering, [[-40.0, 8.0, 15.0, 0.0]])  # room to stop: it answers for its distance
    assert check(mmpc.ego_state(0.0, 8.0, 0.0, 15.0), [[-50.0, 8.0, 25.0, 0.0]])  # a follower in the ego's lane
    assert not check(mmpc.ego_state(0.0, 8.0, 0.0, 15.0), [[-12.0, 8.0, 25.0, 0.0]])  # that cannot stop behind it


def test_the_check_is_refused_nothing_on_an_empty_road():
    ego = mmpc.ego_state(0.0, 4.0, 0.0, 25.0).reshape(1, 6)
    verifier = Verifier(ROAD)
    verdict = verifier.check(ego, torch.zeros(1, 0, 4), torch.zeros(1, 0, dtype=torch.bool), torch.tensor([[5.0]]),
                             torch.tensor([[0.0]]))
    assert verdict.verified.tolist() == [[True]]
    assert verdict.lane.tolist() == [[1]] and verdict.deceleration.tolist() == [[5.0]]


class Reckless(Driver):
    """Asks for full acceleration, straight ahead, always."""

    name = "reckless"

    def decide(self, observation: Observation) -> Decision:
        count = observation.ego.shape[0]
        return Decision.command_only(torch.full((count,), 5.0), torch.zeros(count), 0.0)


def adversarial_traffic(verified: bool) -> tuple[torch.Tensor, float]:
    """A reckless driver behind the check, 32 environments x 12 s: a leader that brakes as hard as
    allowed at random moments, cars beside that accelerate and brake at random, and a car in the
    next lane that, once ahead of the ego, cuts in as soon as it is no longer the ego's leader
    by the rule. Returns which environments collided and the ego's mean speed [m/s]."""
    generator = torch.Generator().manual_seed(0)
    envs, sim = 32, SimConfig(lanes=4)
    verifier = Verifier(ROAD, sim)
    driver = VerifiedDriver(Reckless(), verifier) if verified else Reckless()
    driver.reset(envs)
    body = Body(torch.zeros(envs), torch.full((envs,), 4.0), torch.zeros(envs), torch.full((envs,), 20.0))
    # cars: leader in the ego's lane, two in lane 0 and 2 around the ego, one far in lane 2
    x = torch.stack([torch.full((envs,), 40.0), torch.full((envs,), -10.0), torch.full((envs,), 25.0),
                     torch.full((envs,), 60.0)], dim=1) + torch.rand(envs, 4, generator=generator) * 10
    y = torch.tensor([4.0, 0.0, 8.0, 8.0]).expand(envs, 4).clone()
    speed = torch.tensor([18.0, 22.0, 19.0, 15.0]).expand(envs, 4).clone()
    vy = torch.zeros(envs, 4)
    collided = torch.zeros(envs, dtype=torch.bool)
    period, speeds = 0.1, []
    for step in range(120):
        ego = torch.stack([body.x, body.y, body.heading, body.speed, torch.zeros(envs), torch.zeros(envs)], dim=1)
        vehicles = torch.stack([x, y, speed, vy], dim=2)
        decision = driver.decide(Observation(ego, vehicles, torch.ones(envs, 4, dtype=torch.bool)))
        # traffic within the assumptions: accelerations in [-6, 3], no reversing; lateral moves
        # only into a lane where the ego is not the nearest follower (the rule), at 2 m/s
        brake = torch.rand(envs, 4, generator=generator) < 0.05
        acceleration = torch.where(brake, torch.full((envs, 4), -6.0), torch.rand(envs, 4, generator=generator) * 9 - 6)
        acceleration[:, 3] = -6.0  # the far car brakes to rest: a wall
        ego_on_lane_1 = (counted_lanes(body.y, ROAD, 1.0) == 1).any(dim=1)  # as MOBIL counts it
        cut_in = (x[:, 2] > body.x + 6) & ~ego_on_lane_1 & (y[:, 2] > 4.0)  # the ego not its follower there: may enter
        vy = torch.zeros(envs, 4)
        vy[:, 2] = torch.where(cut_in | ((y[:, 2] < 8.0) & (y[:, 2] > 4.0)), -2.0, 0.0)
        y = torch.clamp(y + vy * period, min=torch.tensor([4.0, 0.0, 4.0, 8.0]))
        x = x + speed * period
        speed = (speed + acceleration * period).clamp_min(0.0)
        body = drive(body, decision.acceleration, decision.steering, verifier.length, sim)
        hits = rectangle_meets_box(body.x[:, None], body.y[:, None], body.heading[:, None], 2.5, 1.0, x - 2.5, x + 2.5,
                                   y - 1.0, y + 1.0)
        collided |= hits.any(dim=1)
        speeds.append(body.speed.mean())
    return collided, float(torch.stack(speeds).mean())


def test_verified_driving_never_collides_with_adversarial_traffic_within_the_assumptions():
    collided, speed = adversarial_traffic(verified=True)
    assert not bool(collided.any())
    assert speed > 5.0  # it drives
    reckless, _ = adversarial_traffic(verified=False)
    assert int(reckless.sum()) > len(reckless) // 2  # the traffic is a threat


def test_an_evaluation_writes_the_verification_columns(tmp_path):
    from mmpc.evaluate import evaluate
    from mmpc.evaluate.store import read_episodes
    from mmpc.evaluate.tasks import EvaluationConfig

    scenario = load_scenario("high_speed", {"sim": "batched", "duration": 1.0})
    evaluate([scenario], tmp_path, EvaluationConfig(drivers=("verified:frenet", "frenet"), seeds=(3,), report=False))
    rows = {row["driver"]: row for row in read_episodes(tmp_path / "episodes.csv")}
    assert 0.0 <= rows["verified:frenet"]["verified_share"] <= 1.0 and rows["frenet"]["verified_share"] is None
    assert rows["verified:frenet"]["assumption_violations"] == 0 and rows["frenet"]["failsafe_steps"] == 0
    assert rows["frenet"]["crash_collider_outside"] is None


def test_the_verified_spec_wraps_any_driver_and_fills_the_new_columns():
    scenario = load_scenario("high_speed", {"sim": "batched", "duration": 1.0})
    driver = make_driver("verified:frenet", scenario)
    assert isinstance(driver, VerifiedDriver) and driver.name == "verified:frenet"
    (result,) = run_lockstep(scenario, [3], driver=driver)
    assert 0.0 <= result.metrics["verified_share"] <= 1.0
    assert result.metrics["failsafe_steps"] >= 0
    assert result.metrics["assumption_violations"] == 0 and result.metrics["crash_collider_outside"] is None
    (plain,) = run_lockstep(scenario, [3], driver=make_driver("frenet", scenario))
    assert plain.metrics["verified_share"] is None and plain.metrics["failsafe_steps"] == 0
    with pytest.raises(ValueError, match="verified:mpc"):
        make_driver("verified", scenario)


def test_the_check_refuses_bad_input():
    verifier = Verifier(ROAD)
    ego = mmpc.ego_state(0.0, 4.0, 0.0, 20.0).reshape(1, 6)
    cars, mask, command = torch.zeros(1, 2, 4), torch.ones(1, 2, dtype=torch.bool), torch.zeros(1, 1)
    with pytest.raises(ValueError, match=r"`ego` must be \(E, 6\)"):
        verifier.check(ego[0], cars, mask, command, command)
    with pytest.raises(ValueError, match="`vehicles` must be"):
        verifier.check(ego, cars[..., :2], mask, command, command)
    with pytest.raises(ValueError, match="`mask` must be a bool"):
        verifier.check(ego, cars, mask.float(), command, command)
    with pytest.raises(ValueError, match="must be finite"):
        verifier.check(ego, cars.clone().fill_(float("nan")), mask, command, command)
    with pytest.raises(ValueError, match="commands must be finite"):
        verifier.check(ego, cars, mask, command + float("inf"), command)
    absent = cars.clone().fill_(float("nan"))  # an absent car's row is not read
    assert verifier.check(ego, absent, ~mask, command, command).verified.tolist() == [[True]]


def test_a_crash_says_whether_the_collider_had_left_its_set():
    """A reckless ego runs into the traffic ahead: the car it hits kept its assumptions."""
    scenario = load_scenario("high_speed", {"sim": "batched", "duration": 20.0})
    results = run_lockstep(scenario, [3, 4, 5, 6], driver=Reckless())
    crashed = [result for result in results if result.metrics["collisions"]]
    assert crashed
    assert all(result.metrics["crash_collider_outside"] == 0 for result in crashed)
    assert all(result.metrics["assumption_violations"] >= 0 for result in results)
