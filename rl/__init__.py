"""mmpc.rl: the batch optimizer as a safe action layer for reinforcement learning.

An RL agent (stable-baselines3) chooses goals; the multi-modal MPC turns them into kinematically
feasible, collision-avoiding trajectories (:mod:`mmpc.rl.safety`). Importing this package
registers the gymnasium environments (the modules themselves load on ``gym.make``):

- ``mmpc/SafeHighway-v0``: discrete goals, lane offset x target speed (DQN, PPO);
- ``mmpc/SafeHighwayContinuous-v0``: Box goals, lateral target and speed (SAC, PPO).

Both accept ``gym.make(id, scenario=..., config=..., reward=...)`` (see
:class:`mmpc.rl.envs.SafeHighwayEnv`).
"""

from gymnasium.envs.registration import register, registry

#: The registered environment ids.
ENV_IDS = ("mmpc/SafeHighway-v0", "mmpc/SafeHighwayContinuous-v0")

for _env_id, _continuous in zip(ENV_IDS, (False, True)):
    if _env_id not in registry:
        register(id=_env_id, entry_point="mmpc.rl.envs:SafeHighwayEnv", kwargs={"continuous": _continuous})
