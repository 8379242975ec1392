"""The driver interface: the registry, the MPC driver, and lockstep episodes (one driver call
per step for several episodes)."""

import pytest
import torch

from mmpc.highway.runner import run_episode, run_lockstep
from mmpc.drivers import Decision, Driver, MPCDriver, Observation, make_driver
from mmpc.scenario import ScenarioConfig

pytestmark = pytest.mark.usefixtures("one_thread")


class CountingDriver(Driver):
    """Keeps lane at constant speed and records every call's batch size and env ids."""

    name = "counting"

    def __init__(self):
        self.calls = []

    def decide(self, observation: Observation) -> Decision:
        self.calls.append(observation.ids().tolist())
        count = observation.num_envs
        return Decision.command_only(torch.zeros(count), torch.zeros(count), 0.1)


def test_registry_builds_the_mpc_and_rejects_unknown_specs():
    scenario = ScenarioConfig(duration=1.0)
    assert isinstance(make_driver("mpc", scenario), MPCDriver)
    with pytest.raises(ValueError, match="unknown driver 'magic'.*expected one of"):
        make_driver("magic", scenario)
    with pytest.raises(ValueError, match="takes no argument"):
        make_driver("mpc:x", scenario)
    with pytest.raises(ValueError, match="non-empty"):
        make_driver("", scenario)


def test_lockstep_makes_one_driver_call_per_step_for_all_episodes():
    scenario = ScenarioConfig(duration=1.0)
    driver = CountingDriver()
    results = run_lockstep(scenario, [4, 5, 6], driver=driver)
    assert [r.seed for r in results] == [4, 5, 6]
    assert len(driver.calls) == 10 and all(call == [0, 1, 2] for call in driver.calls)
    assert all(r.metrics["steps"] == 10 for r in results)
    assert all(r.records[0].goal_index == -1 and r.records[0].plan_cost != r.records[0].plan_cost for r in results)
    with pytest.raises(ValueError, match="distinct"):
        run_lockstep(scenario, [1, 1], driver=driver)


def test_lockstep_mpc_episodes_match_the_episodes_driven_alone():
    scenario = ScenarioConfig(duration=2.0)
    together = run_lockstep(scenario, [0, 1])
    for result in together:
        alone = run_episode(scenario, result.seed)
        assert len(alone.records) == len(result.records)
        for a, b in zip(alone.records, result.records):
            assert a.x == pytest.approx(b.x, abs=1e-3) and a.v == pytest.approx(b.v, abs=1e-3)
            assert a.goal_index == b.goal_index
