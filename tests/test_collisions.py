"""What a collision struck of the ego, and whose fault it was: the geometry, and real crashes
in highway-env (scripted scenes) and on the batched simulator, through mmpc's episode runner."""

import dataclasses
import math

import pytest
import torch

from mmpc.collisions import CRASH_COLUMNS, crash_scene, is_ego_fault, struck_part
from mmpc.drivers import Decision, Driver, Observation
from mmpc.highway import run_episode, run_lockstep
from mmpc.scenario import EgoConfig, load_scenario
from mmpc.traffic_config import ScriptedTraffic, ScriptedVehicle

CAR = (5.0, 2.0)


@pytest.mark.parametrize("other, part", [
    ((4.9, 0.5), "front"),   # rear-ended a car ahead
    ((-4.9, -0.5), "rear"),  # rear-ended by a car behind
    ((1.0, 1.9), "side"),    # side by side
    ((-4.0, 1.8), "side"),   # cut in ahead of a car in the target lane: its front meets the ego's flank
    ((-4.5, 1.2), "rear"),   # a car behind, slightly offset
])
def test_the_part_struck_is_the_face_the_colliders_centre_lies_beyond(other, part):
    assert struck_part((0.0, 0.0, 0.0), [other, (60.0, 0.0)], CAR) == part


def test_the_part_struck_is_measured_in_the_egos_frame_and_the_nearest_car_is_the_collider():
    heading = math.radians(30.0)  # a car straight behind the turned ego, another far ahead
    behind = (-4.8 * math.cos(heading), -4.8 * math.sin(heading))
    assert struck_part((10.0, 2.0, heading), [(10.0 + behind[0], 2.0 + behind[1]), (40.0, 2.0)], CAR) == "rear"
    assert struck_part((0.0, 0.0, 0.0), [(-5.5, 0.0), (4.9, 0.0)], CAR) == "front"  # nearer in footprint units
    assert struck_part((0.0, 0.0, 0.0), [], CAR) is None


def test_fault_follows_the_part_and_bad_input_is_refused():
    assert is_ego_fault("front") and is_ego_fault("side") and not is_ego_fault("rear")
    with pytest.raises(ValueError, match="part"):
        is_ego_fault("roof")
    with pytest.raises(ValueError, match="vehicle"):
        struck_part((0.0, 0.0, 0.0), [(1.0, 0.0)], (0.0, 2.0))


def test_the_crash_scene_names_the_collider_and_how_both_moved():
    turned = math.radians(12.0)
    others = [(60.0, 8.0, 20.0, 0.0), (3.0, 6.2, 8.0 * math.cos(turned), 8.0 * math.sin(turned))]
    crash = crash_scene((100.0 - 100.0, 4.9, 0.0, 19.0), others, CAR, 4.0)
    assert crash.part == "side"
    assert crash.along == pytest.approx(3.0) and crash.across == pytest.approx(1.3)
    assert crash.other_heading_deg == pytest.approx(12.0) and crash.other_speed == pytest.approx(8.0)
    assert crash.closing_speed == pytest.approx(19.0 - 8.0 * math.cos(turned))
    assert crash.ego_offset == pytest.approx(0.9)  # lane 1's centre is y = 4
    assert crash_scene((0.0, 0.0, 0.0, 10.0), [], CAR, 4.0) is None
    with pytest.raises(ValueError, match="lane_width"):
        crash_scene((0.0, 0.0, 0.0, 10.0), others, CAR, 0.0)


class HoldSpeed(Driver):
    """Holds its speed and heading whatever is around (the worst user of a lane)."""

    name = "hold-speed"

    def reset(self, num_envs):
        pass

    def decide(self, observation: Observation) -> Decision:
        count = observation.ego.shape[0]
        return Decision.command_only(torch.zeros(count), torch.zeros(count), 0.0)


def _scripted(speed, vehicle):
    scenario = load_scenario("cruise")
    return dataclasses.replace(scenario, name="scripted_crash", duration=6.0, ego=EgoConfig(speed=speed, lane=1),
                               traffic=ScriptedTraffic((vehicle,)))


def test_highway_env_running_into_a_slow_car_is_the_egos_fault():
    result = run_episode(_scripted(20.0, ScriptedVehicle(lane=1, x=25.0, speed=5.0, constant_speed=True)), 0,
                         driver=HoldSpeed())
    assert result.metrics["collisions"] == 1
    assert result.metrics["collision_part"] == "front" and result.metrics["ego_fault_collisions"] == 1
    metrics = result.metrics  # the scene: 20 m/s straight into a 5 m/s car ahead in the ego's lane centre
    assert metrics["crash_time"] == result.records[-1].time
    # at the impact: touching, or overlapping by at most one frame's closing (15 m/s x 0.1 s)
    assert 5.0 - 1.5 <= metrics["crash_along"] <= 5.0 and abs(metrics["crash_across"]) < 0.5
    assert abs(metrics["crash_other_heading_deg"]) < 1.0 and metrics["crash_closing_speed"] == pytest.approx(15.0, abs=0.5)
    assert abs(metrics["crash_ego_offset"]) < 0.1 and metrics["crash_ego_speed"] == pytest.approx(20.0, abs=0.5)
    assert metrics["crash_fallback_steps"] == 0  # the hold-speed driver has no fallback


def test_highway_env_being_run_into_from_behind_is_not_the_egos_fault():
    result = run_episode(_scripted(5.0, ScriptedVehicle(lane=1, x=-25.0, speed=25.0, constant_speed=True)), 0,
                         driver=HoldSpeed())
    assert result.metrics["collisions"] == 1
    assert result.metrics["collision_part"] == "rear" and result.metrics["ego_fault_collisions"] == 0


def test_no_collision_no_part():
    result = run_episode(_scripted(10.0, ScriptedVehicle(lane=1, x=40.0, speed=10.0, constant_speed=True)), 0,
                         driver=HoldSpeed())
    assert result.metrics["collisions"] == 0
    assert result.metrics["collision_part"] is None and result.metrics["ego_fault_collisions"] == 0
    assert all(result.metrics[column] is None for column in CRASH_COLUMNS)


class FullThrottle(HoldSpeed):
    """Accelerates straight ahead into whatever is in its lane."""

    name = "full-throttle"

    def decide(self, observation: Observation) -> Decision:
        count = observation.ego.shape[0]
        return Decision.command_only(torch.full((count,), 5.0), torch.zeros(count), 0.0)


def test_batched_simulator_collisions_get_their_part_too():
    scenario = dataclasses.replace(load_scenario("cruise"), sim="batched", duration=8.0)
    results = run_lockstep(scenario, [0, 1, 2], driver=FullThrottle())
    crashed = [r for r in results if r.metrics["collisions"]]
    assert crashed, "full throttle through dense traffic should hit someone"
    for result in crashed:
        assert result.metrics["collision_part"] in ("front", "side")
        assert result.metrics["ego_fault_collisions"] == 1


# ------------------------------------------------------------------ read at the impact, not after the push
# Both worlds separate two cars predicted to meet within a frame by half the minimum translation each, in
# the frame that marks them crashed; a fast car meeting another bumper to bumper is pushed sideways when
# the overlap predicted along the road exceeds the cars' width. The scene is read before that push.


def test_highway_env_a_car_driven_straight_into_a_stopped_one_is_struck_at_the_front():
    """The issue's first reproduction: a wall of stopped cars 25 m ahead of an ego at 30 m/s (frenet)
    was read as a side strike with the ego 1 m off its lane centre (the push)."""
    from mmpc.drivers import make_driver

    wall = ScriptedTraffic(tuple(ScriptedVehicle(lane=k, x=25.0, speed=0.0, constant_speed=True) for k in range(6)))
    scenario = dataclasses.replace(load_scenario("cruise"), duration=3.0, ego=EgoConfig(speed=30.0, lane=2), traffic=wall)
    metrics = run_episode(scenario, 0, driver=make_driver("frenet", scenario)).metrics
    assert metrics["collisions"] == 1 and metrics["collision_part"] == "front", metrics
    assert abs(metrics["crash_ego_offset"]) < 0.1 and abs(metrics["crash_across"]) < 0.1, metrics


@pytest.mark.parametrize("behind", [-20.0, -20.25, -20.5, -20.75])
def test_highway_env_a_fast_car_running_into_a_boxed_in_mpc_ego_strikes_its_rear(behind):
    """The issue's second reproduction: a car at 30 m/s behind the MPC ego at 5 m/s, boxed in on both
    sides; where it arrives decides the push (-20.25 and -20.5 were read as side strikes, the ego's fault)."""
    box = ScriptedTraffic((ScriptedVehicle(lane=2, x=behind, speed=30.0, constant_speed=True),
                           ScriptedVehicle(lane=1, x=0.0, speed=5.0, constant_speed=True),
                           ScriptedVehicle(lane=3, x=0.0, speed=5.0, constant_speed=True)))
    scenario = dataclasses.replace(load_scenario("cruise"), duration=3.0, ego=EgoConfig(speed=5.0, lane=2), traffic=box)
    metrics = run_episode(scenario, 0).metrics
    assert metrics["collisions"] == 1, metrics
    assert metrics["collision_part"] == "rear" and metrics["ego_fault_collisions"] == 0, metrics
    assert abs(metrics["crash_ego_offset"]) < 0.5 and abs(metrics["crash_across"]) < 0.5, metrics


#: (ego speed, other's offset along the road, other's speed) [m/s, m, m/s], the ego on lane 2's centre and
#: the other on the same lane; after one frame they are 0.4 m apart, predicted to overlap by more than
#: their width, so the push is sideways.
MEETINGS = {"front": (30.0, 5.0 + 3.0 + 0.4, 0.0), "rear": (5.0, -(5.0 + 2.5 + 0.4), 30.0)}


def _impact_scene(world, scenario):
    """Zero commands until the ego crashes; the crash scene read at the impact, and after the push."""
    for _ in range(5):
        world.apply([0], torch.zeros(1), torch.zeros(1))
        if world.episodes[0].ego.crashed:
            break
    assert world.episodes[0].ego.crashed

    def scene(observation):
        ego, vehicles = observation.ego[0].tolist(), observation.vehicles[0]
        if observation.vehicle_mask is not None:
            vehicles = vehicles[observation.vehicle_mask[0]]
        return crash_scene(tuple(ego[:4]), vehicles.tolist(), scenario.vehicle, scenario.road.lane_width)

    return scene(world.observe_impact(0)), scene(world.observe([0])[0])


@pytest.mark.parametrize("part", ["front", "rear"])
def test_both_worlds_read_the_same_meeting_at_the_impact(part):
    from mmpc.highway import BatchedWorld, HighwayEnvWorld
    from mmpc.sim import vehicle_state

    ego_speed, along, other_speed = MEETINGS[part]
    cruise = load_scenario("cruise")
    scripted = dataclasses.replace(cruise, ego=EgoConfig(speed=ego_speed, lane=2), traffic=ScriptedTraffic(
        (ScriptedVehicle(lane=2, x=along, speed=other_speed, constant_speed=True),)))
    highway = HighwayEnvWorld.start(scripted, [0])
    batched = BatchedWorld.start(dataclasses.replace(cruise, sim="batched"), [0])
    batched.sim.state = vehicle_state(torch.tensor([[0.0, along]]), torch.tensor([[8.0, 8.0]]),
                                      speed=torch.tensor([[ego_speed, other_speed]]))
    try:
        readings = {name: _impact_scene(world, scripted) for name, world in (("highway-env", highway), ("batched", batched))}
    finally:
        highway.close()
    for name, (impact, pushed) in readings.items():
        assert pushed.part == "side" and abs(pushed.across) == pytest.approx(2.0, abs=0.05), (name, pushed)  # the push
        assert impact.part == part and abs(impact.across) < 0.05 and abs(impact.ego_offset) < 0.05, (name, impact)
    (highway_impact, _), (batched_impact, _) = readings["highway-env"], readings["batched"]
    assert batched_impact.along == pytest.approx(highway_impact.along, abs=0.1)  # the sim's other car runs IDM
