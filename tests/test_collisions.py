"""What a collision struck of the ego, and whose fault it was: the geometry, and real crashes
in highway-env (scripted scenes) and on the batched simulator, through mmpc's episode runner."""

import dataclasses
import math

import pytest
import torch

from mmpc.collisions import CRASH_COLUMNS, crash_scene, is_ego_fault, struck_part
from mmpc.drivers import Decision, Driver, Observation
from mmpc.highway import run_episode, run_lockstep
from mmpc.scenario import EgoConfig, ScriptedTraffic, ScriptedVehicle, load_scenario

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
    assert 4.0 < metrics["crash_along"] < 6.0 and abs(metrics["crash_across"]) < 0.5
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
