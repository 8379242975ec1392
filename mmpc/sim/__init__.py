"""A batched highway simulator in torch: E environments x V vehicles stepped at once, on CPU
or CUDA, in float32 or float64, deterministic, written from highway-env's equations.

What it covers:

- the state (:class:`VehicleState`): position, heading, speed, size, lanes, target speed, lane-change timer, a presence mask;
- highway-env's kinematic bicycle with its command limits (:mod:`mmpc.sim.kinematics`);
- IDM car following and lane keeping of the other vehicles on straight lanes (:mod:`mmpc.sim.idm`);
- their MOBIL lane changes with highway-env's timers, safety and politeness criteria, left/right
  order and abort rule, and steering to the target lane (:mod:`mmpc.sim.mobil`);
- the ego driven by (acceleration, steering) commands mapped as the project's highway-env path maps them (:mod:`mmpc.sim.ego`);
- rectangle collisions by separating axes, with highway-env's pre-check, pushes and crash braking (:mod:`mmpc.sim.collision`);
- random IDM traffic of a scenario placed as highway-env places it, the window that keeps it
  around the ego (:mod:`mmpc.sim.traffic`, draws by :mod:`mmpc.sim.random`);
- E episodes of a scenario with time limits and per-environment resets (:class:`SimEpisodes`);
- threatening traffic within the rules (scenario ``traffic.threats``) and orders to single cars
  (a red-team agent's), carried out within the rules (:mod:`mmpc.sim.threats`);
- highway-env's ``Kinematics`` observation and reward of the egos (:mod:`mmpc.sim.observation`,
  :mod:`mmpc.sim.reward`).

Not there yet:

- routes (the route-constrained branch of highway-env's MOBIL);
- scripted and NGSIM traffic (refused: ``--sim highway-env``);
- lane ends: highway-env's lanes run from x = 0 to 10 km, here they are unbounded (behind x = 0 a
  vehicle here still changes lane and counts as a neighbour; in highway-env it does neither).
"""

from mmpc.sim.collision import PolygonTest, handle_collisions, pair_collisions, polygons_intersecting, rectangle_corners
from mmpc.sim.config import SimConfig
from mmpc.sim.ego import ego_action
from mmpc.sim.episodes import SimEpisodes
from mmpc.sim.idm import idm_acceleration, idm_between, lane_keeping_steering, traffic_command, vehicle_ahead, vehicle_behind
from mmpc.sim.kinematics import bicycle_step, limit_command
from mmpc.sim.observation import kinematics_observation
from mmpc.sim.reward import highway_reward
from mmpc.sim.mobil import abort_blockers, advance_timers, change_lanes, mobil_accepts
from mmpc.sim.simulator import HighwaySimulator
from mmpc.sim.state import VehicleState, check_state, lane_of, vehicle_state

__all__ = [
    "HighwaySimulator", "PolygonTest", "SimConfig", "SimEpisodes", "VehicleState", "abort_blockers", "advance_timers", "bicycle_step",
    "change_lanes", "check_state", "ego_action", "handle_collisions", "highway_reward", "idm_acceleration", "idm_between",
    "kinematics_observation", "lane_keeping_steering", "lane_of", "limit_command", "mobil_accepts", "pair_collisions", "polygons_intersecting",
    "rectangle_corners", "traffic_command", "vehicle_ahead", "vehicle_behind", "vehicle_state",
]
