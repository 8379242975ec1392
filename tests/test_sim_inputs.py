"""Bad input to the batched simulator's episodes and the device checks (issue 44, items 5, 6
and 11): every refusal names the argument, what came and what is allowed."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from mmpc.problem import require_on_device, usable_device
from mmpc.scenario import ScenarioConfig
from mmpc.sim import SimEpisodes

SHORT = dataclasses.replace(ScenarioConfig(), duration=2.0)


def test_reset_with_a_bool_mask_resets_the_marked_environments():
    episodes = SimEpisodes(SHORT, [0, 1, 2])
    episodes.step(torch.zeros(3, 2))
    before = episodes.state
    episodes.reset(torch.tensor([False, True, False]), [6])
    assert episodes.seeds.tolist() == [0, 6, 2] and episodes.steps.tolist() == [1, 0, 1]
    fresh = SimEpisodes(SHORT, [6])
    assert torch.equal(episodes.state.x[1], fresh.state.x[0])
    for env in (0, 2):  # the environments left unmarked keep their episode
        assert torch.equal(episodes.state.x[env], before.x[env])


@pytest.mark.parametrize("envs, seeds, message", [
    (torch.tensor([False, True, False]), [5, 6, 7], r"`seeds` must hold one seed per environment reset \(1\); got 3"),
    (torch.tensor([True, False]), [5], r"`envs` as a bool mask must have shape \(3,\); got \(2,\)"),
    (torch.tensor([0, 0]), [5, 6], r"`envs` must not repeat an environment; got \[0, 0\]"),
    ([2, 2], [5, 6], r"`envs` must not repeat an environment"),
    (torch.tensor([1.7]), [5], "`envs` must be a sequence of ints; got a torch.float32 tensor"),
    ([1.0], [5], r"`envs` must be a sequence of ints; got 1.0 \(float\)"),
    ([True, False], [5, 6], r"`envs` must be a sequence of ints; got True \(bool\)"),
    ([3], [5], r"`envs` must lie in \[0, 2\]; got 3"),
    ([-1], [5], "`envs` must be >= 0; got -1"),
    ([1], ["abc"], r"`seeds` must be a sequence of ints; got 'abc' \(str\)"),
])
def test_bad_resets_are_refused_and_change_nothing(envs, seeds, message):
    episodes = SimEpisodes(SHORT, [0, 1, 2])
    before = episodes.state
    with pytest.raises(ValueError, match=message):
        episodes.reset(envs, seeds)
    assert episodes.seeds.tolist() == [0, 1, 2] and all(torch.equal(a, b) for a, b in zip(episodes.state, before))


@pytest.mark.parametrize("running, error, message", [
    (0.5, TypeError, r"`running` must be a bool tensor of shape \(2,\); got float"),
    (1, TypeError, r"`running` must be a bool tensor of shape \(2,\); got int"),
    ([True, False], TypeError, r"`running` must be a bool tensor of shape \(2,\); got list"),
    (torch.tensor([0.5, 1.0]), TypeError, "got a torch.float32 tensor"),
    (torch.tensor([1, 0]), TypeError, "got a torch.int64 tensor"),
    (torch.tensor([True, False, True]), ValueError, r"`running` must have shape \(2,\); got \(3,\)"),
    (torch.tensor([True, False], device="meta"), ValueError, r"`running` is on meta but the episodes' state is on cpu"),
])
def test_step_takes_running_as_a_bool_tensor_on_the_episodes_device(running, error, message):
    episodes = SimEpisodes(SHORT, [0, 1])
    with pytest.raises(error, match=message):
        episodes.step(torch.zeros(2, 2), running)
    assert episodes.steps.tolist() == [0, 0]
    episodes.step(torch.zeros(2, 2), torch.tensor([True, False]))
    assert episodes.steps.tolist() == [1, 0]


@pytest.mark.parametrize("seeds", [[np.uint64(3), np.uint64(4)], np.array([3, 4], dtype=np.uint64),
                                   np.array([3, 4], dtype=np.int32), torch.tensor([3, 4], dtype=torch.int32), (3, 4)])
def test_numpy_and_tensor_integer_seeds_are_seeds(seeds):
    episodes = SimEpisodes(SHORT, seeds)
    assert episodes.seeds.dtype == torch.int64 and episodes.seeds.tolist() == [3, 4]
    assert torch.equal(episodes.state.x, SimEpisodes(SHORT, [3, 4]).state.x)


@pytest.mark.parametrize("seeds, kwargs, message", [
    ("abc", {}, "`seeds` must be a sequence of ints; got 'abc'"),
    (["abc"], {}, r"`seeds` must be a sequence of ints; got 'abc' \(str\) in it"),
    (7, {}, "`seeds` must be a sequence of ints; got 7"),
    (np.array([2**63 + 5], dtype=np.uint64), {}, r"`seeds` must lie in \[0, 9223372036854775807\]; got 9223372036854775813"),
    ([2**70], {}, r"`seeds` must lie in \[0, 9223372036854775807\]"),
    ([[1, 2]], {}, r"`seeds` must be a sequence of ints; got \[1, 2\] \(list\)"),
    ([0, 1], {"device": "meta"}, "`device` must be a device that holds data, such as 'cpu' or 'cuda:0'; got meta"),
    (torch.tensor([0, 1], device="meta"), {}, "`device` must be a device that holds data"),
    ([0, 1], {"device": "gpu"}, "`device` must name a torch device such as 'cpu' or 'cuda:0'; got 'gpu'"),
    (torch.tensor([0, 1], device="meta"), {"device": "cpu"}, "`seeds` is on meta but the episodes' state is on cpu"),
])
def test_bad_seeds_and_devices_are_refused_by_name(seeds, kwargs, message):
    with pytest.raises(ValueError, match=message):
        SimEpisodes(SHORT, seeds, **kwargs)


def test_usable_device_names_the_argument():
    assert usable_device("cpu") == torch.device("cpu")
    with pytest.raises(ValueError, match="`where` must name a torch device"):
        usable_device(3.5, "where")
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="`device` is cuda, which this machine cannot use"):
            usable_device("cuda")


def test_require_on_device_names_the_tensor_and_its_owner():
    """What MPC.build_problem needs before its value checks: a meta ``ego`` fails there with
    "Tensor.item() cannot be called on meta tensors"."""
    ego = torch.zeros(1, 6, device="meta")
    require_on_device(torch.device("cpu"), "the optimizer", ego=torch.zeros(1, 6), vehicle_mask=None, vehicles=[1.0])
    with pytest.raises(ValueError, match=r"^`ego` is on meta but the optimizer is on cpu; move it with .to\(\)$"):
        require_on_device(torch.device("cpu"), "the optimizer", ego=ego, vehicles=torch.zeros(1, 0, 4))
