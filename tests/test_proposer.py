"""The mode proposer: listwise targets and loss, the network and its checkpoint, the driver that
solves only the proposed goals (and escalates), the labelling driver, resumable labels as Minari
datasets, and the DAgger loop through the command line."""

import dataclasses
import json
import math

import numpy as np
import pytest
import torch

from mmpc.drivers import MPCDriver, make_driver
from mmpc.highway.worlds import make_world
from mmpc.imitation.features import STORED_NEIGHBOURS, scene_geometry
from mmpc.imitation.labels import RankingExpert, goal_count, label_episodes, ranking_fields, read_labels
from mmpc.imitation.listwise import (
    ProposerTrainConfig, RankingLabels, feasible_recall, listmle_loss, ranking_targets, top_k_agreement, train_proposer,
)
from mmpc.imitation.policy import load_policy
from mmpc.imitation.proposer import ModeProposer, ProposerConfig, load_proposer, save_proposer
from mmpc.imitation.proposer_dagger import ProposerDaggerConfig
from mmpc.imitation.proposer_driver import ProposerDriver, ego_lane_stop_goal, problem_rows
from mmpc.problem import EGO_Y, ProblemBatch
from mmpc.scenario import build_mpc, load_scenario

SMALL = ProposerConfig(hidden=(32,))


@pytest.fixture(scope="module")
def scenario():
    return load_scenario("high_speed").replace(sim="batched", duration=0.5)


@pytest.fixture(scope="module")
def mpc(scenario):
    return build_mpc(scenario)


@pytest.fixture(scope="module")
def states(scenario):
    """The first observation of 6 batched-simulator episodes."""
    observation, _ = make_world(scenario, list(range(500, 506))).observe(range(6))
    return observation


def untrained(scenario, mpc, seed=0):
    torch.manual_seed(seed)
    return ModeProposer(scenario.road, goal_count(mpc), SMALL, scene=scene_geometry(scenario))


def test_ranking_targets_put_the_experts_goal_first_then_the_feasible_ones_by_cost():
    cost = torch.tensor([[5.0, 1.0, 3.0, 2.0, 0.5], [1.0, 2.0, 3.0, 4.0, 5.0]])
    feasible = torch.tensor([[True, True, True, False, True], [False, False, False, False, False]])
    expert = torch.tensor([2, 3])  # row 0: a tie-break chose 2 over cheaper ones; row 1: the fallback's candidate
    places, valid = ranking_targets(cost, feasible, expert, depth=4)
    assert places[0].tolist() == [2, 4, 1, 0]
    assert valid[0].tolist() == [True, True, True, True]
    assert places[1, 0] == 3 and valid[1].tolist() == [True, False, False, False]
    places, valid = ranking_targets(cost[:1], feasible[:1], expert[:1], depth=6)
    assert valid[0].tolist() == [True, True, True, True, False, False]  # 4 feasible goals, 4 places


def test_listmle_is_the_plackett_luce_likelihood_and_prefers_the_experts_order():
    scores = torch.tensor([[2.0, 0.0, 1.0]])
    places, valid = torch.tensor([[0, 2]]), torch.tensor([[True, True]])
    expected = -(math.log(math.exp(2) / (math.exp(2) + 1 + math.exp(1))) + math.log(math.exp(1) / (1 + math.exp(1))))
    assert float(listmle_loss(scores, places, valid)) == pytest.approx(expected, rel=1e-6)
    reversed_order = torch.tensor([[0.0, 2.0, 1.0]])
    assert float(listmle_loss(reversed_order, places, valid)) > float(listmle_loss(scores, places, valid))
    # an invalid place adds nothing
    assert float(listmle_loss(scores, places, torch.tensor([[True, False]]))) == pytest.approx(
        -math.log(math.exp(2) / (math.exp(2) + 1 + math.exp(1))), rel=1e-6)


def test_agreement_and_recall_count_the_top_k():
    scores = torch.tensor([[3.0, 2.0, 1.0, 0.0], [0.0, 1.0, 2.0, 3.0]])
    assert top_k_agreement(scores, torch.tensor([1, 1]), keep=2) == 0.5
    feasible = torch.tensor([[False, False, True, True], [False, False, False, False]])
    assert feasible_recall(scores, feasible, keep=2) == 0.0  # only row 0 counts; its top 2 are infeasible
    assert feasible_recall(scores, feasible, keep=3) == 1.0


def test_configs_refuse_bad_values_and_a_check_that_is_not_held_out():
    with pytest.raises(ValueError, match="hidden"):
        ProposerConfig(hidden=())
    with pytest.raises(ValueError, match="keep"):
        ProposerTrainConfig(keep=0)
    with pytest.raises(ValueError, match="validation_fraction"):
        ProposerTrainConfig(validation_fraction=1.0)
    with pytest.raises(ValueError, match="overlap"):
        ProposerDaggerConfig(seed_start=100, episodes=10, rounds=1, check_seed_start=115)
    with pytest.raises(ValueError, match="beta"):
        ProposerDaggerConfig(beta=1.5)
    assert ProposerDaggerConfig().beta_of(0) == 1.0 and ProposerDaggerConfig(beta=0.5, beta_decay=0.5).beta_of(3) == 0.125


def test_checkpoint_round_trip_forced_goal_and_refusals(scenario, mpc, tmp_path):
    proposer = untrained(scenario, mpc)
    ego = np.array([[0.0, 8.0, 0.0, 20.0, 0.0, 0.0], [10.0, 20.0, 0.0, 15.0, 0.5, 0.0]])
    neighbours = np.full((2, STORED_NEIGHBOURS, 4), np.nan, dtype=np.float32)
    neighbours[:, 0] = [30.0, 8.0, 10.0, 0.0]
    features = proposer.features(ego, neighbours)
    path = save_proposer(tmp_path / "p.pt", proposer, scenario=scenario.name, info={"keep": 3})
    loaded = load_proposer(path)
    assert torch.equal(loaded(torch.as_tensor(features))[0], proposer(torch.as_tensor(features))[0])
    forced = torch.tensor([7, 33])
    top = loaded.top_goals(features, 3, forced=forced)
    assert top[:, 0].tolist() == [7, 33] and len(set(top[0].tolist())) == 3
    unforced = loaded.top_goals(features, 3)
    assert torch.equal(loaded.top_goals(features, 3, forced=torch.tensor([[-1], [-1]])), unforced)  # -1: none
    with pytest.raises(ValueError, match="count"):
        loaded.top_goals(features, loaded.num_goals + 1)
    with pytest.raises(ValueError, match="shape"):
        loaded(torch.zeros(2, 3))
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="not a readable"):
        load_proposer(tmp_path / "junk.pt")
    with pytest.raises(FileNotFoundError, match="mmpc imitate proposer"):
        load_proposer(tmp_path / "missing.pt")
    with pytest.raises(ValueError, match="not an mmpc policy checkpoint"):  # a checkpoint of the other kind
        load_policy(path)
    damaged = torch.load(path, weights_only=True)
    del damaged["num_goals"]
    torch.save(damaged, tmp_path / "damaged.pt")
    with pytest.raises(ValueError, match="lacks 'num_goals'"):
        load_proposer(tmp_path / "damaged.pt")
    with pytest.raises(ValueError, match="checkpoint path"):
        make_driver("proposer", scenario)
    cruise = load_scenario("cruise")  # another goal set (34 goals, not 35)
    driver = make_driver(f"proposer:{path}", cruise)
    assert driver.keep == 3
    with pytest.raises(ValueError, match="goal set"):
        driver.decide(make_world(cruise.replace(sim="batched"), [0]).observe([0])[0])


def test_the_stop_goal_kept_is_on_the_egos_lane(mpc, states):
    problem = mpc.build_problem(states.ego, states.vehicles, states.vehicle_mask)
    for lane in range(mpc.road.num_lanes):
        ego = states.ego.clone()
        ego[:, EGO_Y] = lane * mpc.road.lane_width + 0.3
        slot = ego_lane_stop_goal(mpc, ego, problem.num_goals)
        goals = mpc.build_problem(ego, states.vehicles, states.vehicle_mask).goals
        assert torch.allclose(goals[torch.arange(len(slot)), slot, 1], torch.full((len(slot),), lane * mpc.road.lane_width))
        assert bool((slot >= problem.num_goals - 3).all())  # among the stop goals, which come last


def test_keeping_every_goal_drives_exactly_as_the_mpc(scenario, mpc, states):
    proposer = untrained(scenario, mpc)
    full = ProposerDriver(mpc, proposer, keep=proposer.num_goals - 1).decide(states)
    expert = MPCDriver(mpc).decide(states)
    assert torch.equal(full.goal_index, expert.goal_index)
    assert torch.allclose(full.acceleration, expert.acceleration, atol=1e-5)
    assert torch.allclose(full.steering, expert.steering, atol=1e-6)
    assert torch.equal(full.fallback, expert.fallback)


def test_escalated_rows_keep_their_obstacles():
    problem = ProblemBatch(torch.zeros(3, 6), torch.zeros(3, 5, 2), torch.arange(3 * 4 * 2 * 2.0).view(3, 4, 2, 2),
                           torch.ones(3, 4, dtype=torch.bool), None)
    rows = problem_rows(problem, torch.tensor([2, 0]))
    assert rows.obstacle_axes is None
    assert torch.equal(rows.obstacles, problem.obstacles[[2, 0]]) and rows.obstacle_mask.shape == (2, 4)


def test_a_proposal_without_a_feasible_goal_escalates_to_the_full_set(scenario, states):
    # nothing forced into the proposal; the paper's schedule (every solve cold, 100 iterations) makes goal 11 hopeless
    no_stops = scenario.replace(mpc=dataclasses.replace(scenario.mpc, stop_lanes=None, warm_iterations=0),
                                optimizer=dataclasses.replace(scenario.optimizer, exit_checks=()))
    mpc = build_mpc(no_stops)
    expert = MPCDriver(mpc).decide(states)
    hopeless = 11  # slowing to 4 m/s on the ego's lane: infeasible in all six scenes
    assert not bool(expert.candidates.feasible[:, hopeless].any()) and not bool(expert.fallback.any())
    proposer = untrained(no_stops, mpc)
    with torch.no_grad():
        proposer.head.weight.zero_()
        proposer.head.bias.zero_()
        proposer.head.bias[hopeless] = 5.0
    alone = ProposerDriver(mpc, proposer, keep=1, escalate=False)
    decision = alone.decide(states)
    assert bool(decision.fallback.all()) and alone.escalated_rows == 0
    assert decision.iterations.tolist() == [100] * 6
    assert decision.goal_index.tolist() == [hopeless] * 6
    unsolved = decision.candidates.xy[:, [g for g in range(proposer.num_goals) if g != hopeless]]
    assert bool(torch.isnan(unsolved).all())  # goals it did not solve are drawn as nothing
    escalating = ProposerDriver(mpc, proposer, keep=1)
    decision = escalating.decide(states)
    assert escalating.escalated_rows == 6 and escalating.decided_rows == 6
    assert decision.iterations.tolist() == [200] * 6  # the proposal's solve, then the full set's
    assert not bool(decision.fallback.any())
    assert torch.equal(decision.goal_index, expert.goal_index)
    assert torch.allclose(decision.acceleration, expert.acceleration, atol=1e-5)
    assert decision.candidates.goals.shape == (6, proposer.num_goals, 2)
    decision = escalating.decide(states)  # the goals driven at the last step are kept in the proposal
    assert escalating.escalated_rows == 6 and torch.equal(decision.goal_index, expert.goal_index)
    escalating.reset(6)  # new episodes: nothing driven yet
    escalating.decide(states)
    assert escalating.escalated_rows == 12


def test_the_labelling_driver_labels_the_full_set_whoever_drives(scenario, mpc, states):
    expert = MPCDriver(mpc).decide(states)
    alone = RankingExpert(mpc)
    decision = alone.decide(states)
    labels = alone.labels()
    assert set(labels) == set(ranking_fields(goal_count(mpc)))
    assert torch.equal(decision.goal_index, expert.goal_index)
    assert labels["expert_goal"].tolist() == expert.goal_index.tolist() and not labels["learner_drove"].any()
    assert labels["goal_feasible"].sum(axis=1).tolist() == expert.feasible_goals.tolist()
    proposer = untrained(scenario, mpc, seed=3)
    learner_only = RankingExpert(mpc, proposer, beta=0.0, keep=2)
    decision = learner_only.decide(states)
    labels = learner_only.labels()
    assert labels["expert_goal"].tolist() == expert.goal_index.tolist()  # the label is the expert's either way
    reference = ProposerDriver(mpc, proposer, keep=2).decide(states)
    assert decision.goal_index.tolist() == reference.goal_index.tolist()  # the learner drives as its driver would
    unescalated = ProposerDriver(mpc, proposer, keep=2, escalate=False).decide(states)
    assert labels["learner_drove"].tolist() == (~unescalated.fallback).tolist()  # the expert's pick where it escalates
    with pytest.raises(ValueError, match="no proposer"):
        RankingExpert(mpc, beta=0.5)


def test_behind_the_check_a_goal_is_usable_only_where_its_first_command_verifies(scenario, mpc, states):
    from mmpc.verify import Verifier

    verifier = Verifier.for_scenario(scenario)
    plain, checked = RankingExpert(mpc), RankingExpert(mpc, verifier=verifier)
    plain.decide(states)
    decision = checked.decide(states)
    feasible, usable = plain.labels()["goal_feasible"], checked.labels()["goal_feasible"]
    result = decision.plan.result
    acceleration, steering = mpc.candidate_commands(decision.plan.problem.ego, result.trajectories)
    verdict = verifier.check(states.ego, states.vehicles, states.vehicle_mask, acceleration, steering)
    np.testing.assert_array_equal(usable, feasible & verdict.verified.numpy())
    assert usable.any(axis=1).all() and not usable.all()  # the check rules some feasible goals out here
    expert = checked.labels()["expert_goal"]
    assert usable[np.arange(len(expert)), expert].all()  # the expert's choice is a usable goal
    assert bool(decision.verified.all()) and not bool(decision.failsafe.any())
    assert torch.equal(decision.goal_index, torch.as_tensor(expert))


def test_labels_stream_to_disk_resume_and_load_as_a_minari_dataset(scenario, tmp_path, monkeypatch):
    out = tmp_path / "round_0"
    seeds = [600, 601, 602]
    report = label_episodes(scenario, seeds, out, lockstep=1, dataset_id="mmpc/test-rankings-v0")
    assert sorted(report.generated) == seeds and report.states == 15
    assert json.loads((out / "manifest.json").read_text())["expert"] == "verified:mpc"  # labelled behind the check
    labels = read_labels([out])
    assert labels.num_states == 15 and labels.cost.shape == (15, 35) and labels.feasible.dtype == np.bool_
    assert sorted(set(labels.episodes.tolist())) == [0, 1, 2]
    labels.check()
    (out / "episodes" / "seed_000601.npz").unlink()  # as if interrupted before that episode was staged
    again = label_episodes(scenario, seeds, out, lockstep=1, dataset_id="mmpc/test-rankings-v0")
    assert again.generated == [601]
    relabelled = read_labels([out])
    np.testing.assert_array_equal(relabelled.cost, labels.cost)
    import minari
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(out / "minari"))
    dataset = minari.load_dataset("mmpc/test-rankings-v0")
    assert dataset.total_episodes == 3
    episode = next(dataset.iterate_episodes())
    assert episode.infos["goal_cost"].shape == (6, 35) and episode.infos["expert_goal"].shape == (6,)
    with pytest.raises(Exception, match="another configuration"):
        label_episodes(scenario.replace(duration=1.0), seeds, out, lockstep=1, dataset_id="mmpc/test-rankings-v0")


def test_training_learns_a_ranking_that_follows_the_scene(scenario, mpc):
    rng = np.random.default_rng(0)
    count, goals = 3000, goal_count(mpc)
    ego = np.zeros((count, 6), dtype=np.float32)
    ego[:, EGO_Y] = rng.integers(0, 6, count) * 4.0
    ego[:, 3] = rng.uniform(5, 25, count)
    neighbours = np.full((count, STORED_NEIGHBOURS, 4), np.nan, dtype=np.float32)
    lane = (ego[:, EGO_Y] / 4).astype(int)
    cost = rng.uniform(10, 20, (count, goals)).astype(np.float32)
    cost[np.arange(count), lane] = 0.0  # goal slot = lane index is best, slot lane + 6 second
    cost[np.arange(count), lane + 6] = 1.0
    feasible = np.ones((count, goals), dtype=bool)
    labels = RankingLabels(ego, neighbours, cost, feasible, lane.astype(np.int64), np.arange(count) // 30)
    config = ProposerTrainConfig(epochs=12, batch_size=64, learning_rate=3e-3, keep=1, proposer=SMALL)
    proposer, history = train_proposer(labels, scenario.road, config, scene=scene_geometry(scenario))
    assert history.val_agreement[history.best_epoch] > 0.95  # chance: 1 / 35
    scores, _ = proposer(torch.as_tensor(proposer.features(ego[:200], neighbours[:200])))
    second = scores.topk(2, dim=1).indices[:, 1].numpy()
    assert np.mean(second == lane[:200] + 6) > 0.9  # the second place was learned too
    broken = labels._replace(expert=np.full(count, goals, dtype=np.int64))
    with pytest.raises(ValueError, match="goal slots"):
        train_proposer(broken, scenario.road, config, scene=scene_geometry(scenario))


def test_cli_runs_dagger_rounds_resumes_and_the_proposer_drives_in_evaluate(tmp_path, capsys):
    from mmpc.cli.main import main

    out = tmp_path / "run"
    args = ["imitate", "proposer", "--scenario", "high_speed", "--sim", "batched", "--duration", "0.5", "--rounds", "1",
            "--set", "episodes=2", "--set", "lockstep=2", "--set", "check_episodes=2", "--set", "train.epochs=2",
            "--set", "train.proposer.hidden=[16]", "--out", str(out)]
    rounds = args.index("--rounds") + 1
    assert main(args[:rounds] + ["0"] + args[rounds + 1:]) == 0  # round 0 alone, then extended to round 1
    assert main(args) == 0
    report = json.loads((out / "proposer.json").read_text())
    assert [entry["round"] for entry in report["rounds"]] == [0, 1]
    assert report["rounds"][1]["beta"] == 0.5 and report["rounds"][1]["states"] == 20
    assert report["rounds"][1]["check"]["episodes"] == 2 and "expert_check" in report["rounds"][1]
    assert (out / "labels" / "round_1" / "minari").is_dir() and (out / "proposer.pt").is_file()
    mtime = (out / "round_1" / "proposer.pt").stat().st_mtime
    assert main(args) == 0  # resumed: nothing to do
    assert (out / "round_1" / "proposer.pt").stat().st_mtime == mtime
    assert main(args[:-2] + ["--set", "beta=0.2", "--out", str(out)]) == 2
    assert "another configuration" in capsys.readouterr().err
    assert report["identity"]["config"]["verify"] is True
    recorded = json.loads((out / "proposer.json").read_text())  # a run labelled before the check existed ...
    del recorded["identity"]["config"]["verify"]
    (out / "proposer.json").write_text(json.dumps(recorded))
    assert main(args) == 2 and "--set verify=false" in capsys.readouterr().err
    assert main(args[:-2] + ["--set", "verify=false", "--out", str(out)]) == 0  # ... resumes as it was labelled
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
    events = EventAccumulator(str(out / "tb"))
    events.Reload()
    assert "labels/top_k_agreement" in events.Tags()["scalars"]
    evaluation = tmp_path / "eval"
    assert main(["evaluate", "--driver", f"mpc,proposer:{out / 'proposer.pt'}", "--scenarios", "high_speed",
                 "--sim", "batched", "--seeds", "0-1", "--duration", "0.5", "--out", str(evaluation)]) == 0
    rows = (evaluation / "episodes.csv").read_text().splitlines()
    assert sum(f"proposer:{out / 'proposer.pt'}" in row for row in rows) == 2


def test_the_goal_kept_from_the_last_step_is_found_again_by_place_after_a_lane_change(scenario, mpc, states):
    driver = ProposerDriver(mpc, untrained(scenario, mpc))
    first = states._replace(ego=states.ego[:1].clone(), vehicles=states.vehicles[:1], vehicle_mask=states.vehicle_mask[:1],
                            env_ids=torch.tensor([7]))
    first.ego[0, EGO_Y] = 8.0  # lane 2
    problem = mpc.build_problem(first.ego, first.vehicles, first.vehicle_mask)
    goals = problem.goals[0]
    right_fast = int(((goals[:, 1] == 12.0) & (goals[:, 0] - first.ego[0, 0] == 24.0 * 8.0)).nonzero()[0])
    driver.remember(first, problem, torch.tensor([right_fast]))
    later = first._replace(ego=first.ego.clone())
    later.ego[0, EGO_Y] = 12.0  # the lane change is done: lane 3 is the ego's lane, its slots shifted
    moved = mpc.build_problem(later.ego, later.vehicles, later.vehicle_mask)
    slot = int(driver.previous_goal(later, moved)[0])
    assert slot != right_fast and float(moved.goals[0, slot, 1]) == 12.0
    assert float(moved.goals[0, slot, 0] - later.ego[0, 0]) == pytest.approx(24.0 * 8.0)
    other = later._replace(env_ids=torch.tensor([8]))  # an environment that has not driven yet
    assert driver.previous_goal(other, moved) is None


@pytest.mark.parametrize("name", ["cruise", "high_speed"])
def test_the_shipped_proposers_drive_their_scenario_by_name(name):
    scenario = load_scenario(name).replace(sim="batched")
    driver = make_driver(f"proposer:{name}", scenario)
    assert driver.keep == 4 and driver.proposer.num_goals == goal_count(driver.mpc)
    observation, _ = make_world(scenario, [7, 8]).observe([0, 1])
    decision = driver.decide(observation)
    assert decision.goal_index.shape == (2,) and not bool(decision.fallback.any())
    with pytest.raises(FileNotFoundError, match="shipped proposers: cruise, high_speed"):
        make_driver("proposer:no_such_proposer", scenario)


def test_the_shipped_proposer_drives_behind_the_check():
    from mmpc.highway import run_lockstep

    scenario = load_scenario("cruise", {"sim": "batched", "duration": 2.0})
    driver = make_driver("verified:proposer:cruise", scenario)
    results = run_lockstep(scenario, [71850, 71851], driver=driver)
    assert driver.name == "verified:proposer:cruise"
    assert all(r.metrics["collisions"] == 0 and r.metrics["verified_share"] > 0.9 for r in results)
    assert all(record.verified is not None for r in results for record in r.records)
