"""highway-env as the world the drivers drive in: the only package of mmpc that imports
highway-env or pygame.

:mod:`~mmpc.highway.episode` turns a scenario into a highway-env episode seen in the road frame;
:mod:`~mmpc.highway.traffic` drives the other vehicles (IDM/MOBIL, scripted, NGSIM replay);
:mod:`~mmpc.highway.worlds` is the protocol of the environments of a run (the episode runner's and
the safe RL agent step's): highway-env episodes (:mod:`~mmpc.highway.highway_env_world`), or the
batched simulator (:mod:`~mmpc.highway.batched_world`, :mod:`mmpc.sim`) when the scenario says ``sim: batched``;
:mod:`~mmpc.highway.runner` is the one episode loop (lockstep, with observers);
:mod:`~mmpc.highway.video` draws the driver's candidates into the rendered frames.
"""

from mmpc.highway.episode import (
    ACCELERATION_RANGE,
    STEERING_RANGE,
    HighwayEpisode,
    RoadFrame,
    RoadState,
    command_to_action,
    env_config,
    road_state,
    vehicle_motion,
)
from mmpc.highway.runner import (
    EpisodeResult,
    Observer,
    Step,
    run_episode,
    run_lockstep,
    write_outputs,
)
from mmpc.highway.batched_world import BatchedWorld
from mmpc.highway.highway_env_world import HighwayEnvWorld, stack_observations
from mmpc.highway.worlds import World, make_world

__all__ = [
    "ACCELERATION_RANGE", "STEERING_RANGE", "EpisodeResult", "HighwayEpisode", "Observer", "RoadFrame", "RoadState",
    "command_to_action", "env_config", "road_state", "run_episode", "Step", "run_lockstep", "stack_observations",
    "vehicle_motion", "write_outputs", "BatchedWorld", "HighwayEnvWorld", "World", "make_world",
]
