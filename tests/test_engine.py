"""mmpc.rl.engine.SafeEnvs: the one agent-step engine of every safe environment API, the same over
both worlds (highway-env's episodes and the batched simulator)."""

from __future__ import annotations

import numpy as np
import pytest

from mmpc.config import load_config
from mmpc.rl.config import RLConfig
from mmpc.rl.engine import SafeEnvs
from mmpc.rl.envs import SafeHighwayEnv
from mmpc.rl.vec_env import SafeVecEnv, SafeVectorEnv

pytestmark = pytest.mark.usefixtures("one_thread")

WORLDS = ("highway-env", "batched")
#: The keys every step's ``info`` holds, in both worlds (the layer verifies by default).
INFO_KEYS = {"intervention", "intervention_frames", "fallback_frames", "solved_frames", "frames", "solve_ms", "speed",
             "mean_speed", "crashed", "goal", "feasible_goals", "agent_feasible", "residuals", "verified_frames",
             "failsafe_frames"}


@pytest.fixture(scope="module")
def smoke() -> RLConfig:
    return load_config(RLConfig, "smoke")  # 2 s episodes: 4 agent steps of 0.5 s


@pytest.mark.parametrize("world", WORLDS)
def test_an_agent_step_in_either_world(world, smoke):
    """Observations, rewards and infos of the same shape and meaning; auto-reset starts the ended
    episodes again from drawn seeds, with their last observation kept; without it they wait for reset."""
    scenario = smoke.scenario.replace(sim=world)
    envs = SafeEnvs(2, scenario, smoke.env, smoke.reward, seed=0)
    observations, infos = envs.reset([5, 6])
    size = SafeHighwayEnv(scenario, smoke.env, smoke.reward, layer=envs.layer).observation_space.shape[0]
    assert observations.shape == (2, size) and observations.dtype == np.float32 and [i["episode_seed"] for i in infos] == [5, 6]
    steps = round(scenario.duration * scenario.frequency / smoke.env.decision_frames)
    for index in range(steps):
        step = envs.advance([0, smoke.env.num_actions - 1])
        assert step.rewards.shape == (2,) and step.rewards.dtype == np.float64
        for info in step.infos:
            assert set(info) == INFO_KEYS and info["frames"] == smoke.env.decision_frames
            assert info["verified_frames"] + info["failsafe_frames"] == info["frames"]
    assert step.truncated.all() and not step.terminated.any()  # 2 s are up
    assert sorted(step.final) == [0, 1] and sorted(step.reset_infos) == [0, 1]
    assert envs.seeds == [step.reset_infos[0]["episode_seed"], step.reset_infos[1]["episode_seed"]]
    assert not bool(envs.world.done().any())  # started again
    envs.reset([5, 6])
    for index in range(steps):
        last = envs.advance([0, 0], auto_reset=False)
    assert last.truncated.all() and last.final == {} and last.reset_infos == {}
    assert last.observations.shape == (2, size) and np.isfinite(last.observations).all()  # the ended episodes' last
    with pytest.raises(RuntimeError, match=r"environments \[0, 1\] are over: call reset\(\) first"):
        envs.advance([0, 0])
    envs.close()


def test_every_safe_environment_api_steps_through_the_engine(smoke, monkeypatch):
    """The gymnasium environment, the SB3 VecEnv and the gymnasium VectorEnv are views of one engine."""
    calls = []
    advance = SafeEnvs.advance

    def counted(self, actions, **kwargs):
        calls.append((type(self).__name__, len(actions), kwargs.get("auto_reset", True)))
        return advance(self, actions, **kwargs)

    monkeypatch.setattr(SafeEnvs, "advance", counted)
    single = SafeHighwayEnv(smoke.scenario, smoke.env, smoke.reward)
    single.reset(seed=1)
    single.step(0)
    vec = SafeVecEnv(2, smoke.scenario, smoke.env, smoke.reward)
    vec.reset()
    vec.step(np.array([0, 0]))
    vector = SafeVectorEnv(2, smoke.scenario.replace(sim="batched"), smoke.env, smoke.reward)
    vector.reset(seed=3)
    vector.step(np.array([0, 0]))
    assert calls == [("SafeEnvs", 1, False), ("SafeEnvs", 2, True), ("SafeEnvs", 2, True)]
    for env in (single, vec, vector):
        env.close()
    assert vec.batch.world is None and vector.batch.world is None  # the worlds are released
