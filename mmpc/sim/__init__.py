"""A batched highway simulator in torch: E environments x V vehicles stepped at once, on CPU
or CUDA, in float32 or float64, deterministic, written from highway-env's equations.

What this first slice covers:

- the state (:class:`VehicleState`): position, heading, speed, size, lanes, target speed, a presence mask;
- highway-env's kinematic bicycle with its command limits (:mod:`mmpc.sim.kinematics`);
- IDM car following and lane keeping of the other vehicles on straight lanes (:mod:`mmpc.sim.idm`);
- the ego driven by (acceleration, steering) commands mapped as the project's highway-env path maps them (:mod:`mmpc.sim.ego`);
- rectangle collisions by separating axes, with highway-env's pre-check, pushes and crash braking (:mod:`mmpc.sim.collision`).

Not there yet:

- MOBIL lane changes (target lanes stay as given);
- the window that recycles vehicles around the ego;
- resets and random traffic placement;
- scenarios built from :class:`mmpc.scenario.ScenarioConfig`;
- the gymnasium vector environment (observations, rewards, termination);
- the end of highway-env's 10 km lanes (lanes here are unbounded).
"""

from mmpc.sim.collision import PolygonTest, handle_collisions, pair_collisions, polygons_intersecting, rectangle_corners
from mmpc.sim.config import SimConfig
from mmpc.sim.ego import ego_action
from mmpc.sim.idm import idm_acceleration, lane_keeping_steering, traffic_command, vehicle_ahead
from mmpc.sim.kinematics import bicycle_step, limit_command
from mmpc.sim.simulator import HighwaySimulator
from mmpc.sim.state import VehicleState, check_state, lane_of, vehicle_state

__all__ = [
    "HighwaySimulator", "PolygonTest", "SimConfig", "VehicleState", "bicycle_step", "check_state", "ego_action",
    "handle_collisions", "idm_acceleration", "lane_keeping_steering", "lane_of", "limit_command", "pair_collisions",
    "polygons_intersecting", "rectangle_corners", "traffic_command", "vehicle_ahead", "vehicle_state",
]
