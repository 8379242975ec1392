"""The held-out problem corpus (scripts/build_problem_corpus.py) and its benchmark (scripts/bench_corpus.py):
a tiny corpus built, resumed, read back and checked; bad and corrupt input refused; benchmark rows that add up."""

import json
import shutil

import pytest
import torch

import bench_corpus
import build_problem_corpus as corpus_script
from build_problem_corpus import CorpusError, load_corpus
from mmpc.drivers.batch_nlp import goal_subset
from mmpc.drivers.nlp import SOLVED_STATUSES

#: One 1 s cruise episode, every 4th step (steps 0, 4, 8), 3 of the 29 goals.
TINY = ["--scenarios", "cruise", "--seeds", "cruise=27000", "--duration", "1.0", "--every", "4", "--min-obstacles", "1",
        "--goals", "3", "--min-states", "1", "--chunk", "1"]


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """A tiny corpus, labelled in two runs (one state, then the rest); the file after each run."""
    out = tmp_path_factory.mktemp("corpus")
    previous = torch.get_num_threads()
    try:
        assert corpus_script.main([*TINY, "--label-limit", "1", "--out", str(out)]) == 0
        partial = load_corpus(out / "cruise.pt")
        assert corpus_script.main([*TINY, "--out", str(out)]) == 0
    finally:
        torch.set_num_threads(previous)
    return out, partial


def test_corpus_holds_the_mpc_problems_with_consistent_ipopt_labels(tiny):
    out, _ = tiny
    corpus = load_corpus(out / "cruise.pt")
    states, goals, slots, knots = 3, 3, 6, 41
    assert corpus["ego"].shape == (states, 6) and corpus["goals"].shape == (states, goals, 2)
    assert corpus["obstacles"].shape == (states, slots, 100, 2) and corpus["obstacle_mask"].shape == (states, slots)
    assert corpus["nlp_obstacles"].shape == (states, slots, knots, 2) and corpus["nlp_times"].shape == (knots,)
    assert corpus["seed"].tolist() == [27000] * 3 and corpus["step"].tolist() == [0, 4, 8]
    assert torch.equal(corpus["goal_index"], goal_subset(29, 3))
    assert corpus["recording"]["scenario"] == "cruise" and corpus["episodes"][0]["kept"] == 3
    assert bool(corpus["labelled"].all()) and bool((corpus["obstacle_mask"].sum(dim=1) >= 1).all())
    # Both prediction grids hold t = 0 and t = horizon: the NLP's obstacles are the MPC's slots.
    present = corpus["obstacle_mask"]
    for grid_index, knot_index in ((0, 0), (-1, -1)):
        gap = (corpus["obstacles"][:, :, grid_index].double() - corpus["nlp_obstacles"][:, :, knot_index])[present]
        assert float(gap.abs().max()) < 1e-3
    # Labels: the baseline's rule, IPOPT's own status, times and iterations.
    tolerance = corpus["nlp_config"]["feasibility_tolerance"]
    feasible, violation = corpus["ipopt_feasible"], corpus["ipopt_violation"]
    assert bool((violation[feasible] <= tolerance).all()) and bool((violation[~feasible] > tolerance).all())
    names = corpus["status_names"]
    solved = torch.tensor([[names[c] in SOLVED_STATUSES for c in row] for row in corpus["ipopt_status"].tolist()])
    assert torch.equal(solved, corpus["ipopt_solved"])
    assert bool((corpus["ipopt_solve_ms"] > 0).all()) and bool((corpus["ipopt_iterations"] >= 0).all())
    manifest = json.loads((out / "manifest.json").read_text())
    entry = manifest["scenarios"]["cruise"]
    assert entry["states"] == entry["labelled_states"] == 3 and entry["labelled_goals"] == 9
    assert entry["ipopt_feasible"] == int(feasible.sum()) and sum(entry["ipopt_status_counts"].values()) == 9
    assert manifest["total_ipopt_s"] == pytest.approx(float(corpus["ipopt_solve_ms"].sum()) / 1e3, abs=0.1)
    assert manifest["nlp_config"]["max_iter"] == 100 and "--goals 3" in manifest["command"]


def test_labelling_resumes_where_it_stopped(tiny):
    out, partial = tiny
    corpus = load_corpus(out / "cruise.pt")
    assert partial["labelled"].tolist() == [True, False, False]
    assert bool(torch.isnan(partial["ipopt_violation"][1:]).all()) and bool((partial["ipopt_status"][1:] == -1).all())
    for name in ("ipopt_violation", "ipopt_solve_ms", "ipopt_feasible"):  # the first state was not solved again
        assert torch.equal(partial[name][0], corpus[name][0])
    assert torch.equal(partial["ego"], corpus["ego"]) and torch.equal(partial["obstacles"], corpus["obstacles"])


def test_a_rerun_with_other_settings_is_refused(tiny, capsys):
    out, _ = tiny
    before = (out / "cruise.pt").read_bytes()
    assert corpus_script.main([*TINY[:-2], "--chunk", "2", "--every", "5", "--out", str(out)]) == 2
    assert "other settings" in capsys.readouterr().err
    assert (out / "cruise.pt").read_bytes() == before


def test_truncated_or_foreign_files_are_refused_with_a_clear_error(tiny, tmp_path, capsys):
    out, _ = tiny
    data = (out / "cruise.pt").read_bytes()
    (tmp_path / "cruise.pt").write_bytes(data[: len(data) // 2])
    with pytest.raises(CorpusError, match="truncated or corrupt"):
        load_corpus(tmp_path / "cruise.pt")
    torch.save({"format": "something else"}, tmp_path / "other.pt")
    with pytest.raises(CorpusError, match="not a problem corpus"):
        load_corpus(tmp_path / "other.pt")
    corpus = load_corpus(out / "cruise.pt")
    del corpus["ipopt_violation"]
    torch.save(corpus, tmp_path / "missing.pt")
    with pytest.raises(CorpusError, match="missing fields.*ipopt_violation"):
        load_corpus(tmp_path / "missing.pt")
    with pytest.raises(CorpusError, match="does not exist"):
        load_corpus(tmp_path / "nowhere.pt")
    # The benchmark on a folder with a truncated file stops with the message, writing nothing.
    shutil.copy(out / "manifest.json", tmp_path / "manifest.json")
    assert bench_corpus.main(["--corpus", str(tmp_path), "--compile", "off", "--out", str(tmp_path / "bench")]) == 2
    assert "truncated or corrupt" in capsys.readouterr().err
    assert not (tmp_path / "bench").exists()


def test_bad_input_fails_before_writing(tmp_path, capsys):
    assert corpus_script.main(["--scenarios", "nowhere", "--seeds", "nowhere=1", "--out", str(tmp_path)]) == 2
    assert "shipped scenarios" in capsys.readouterr().err
    assert corpus_script.main(["--scenarios", "cruise_paper", "--out", str(tmp_path)]) == 2
    assert "no seeds for scenario 'cruise_paper'" in capsys.readouterr().err
    empty = [*TINY[:TINY.index("--min-obstacles")], "--min-obstacles", "7", "--out", str(tmp_path)]  # 6 slots: never dense
    assert corpus_script.main(empty) == 2
    assert "no dense state" in capsys.readouterr().err
    assert not list(tmp_path.glob("*.pt"))


def test_benchmark_rows_add_up_and_refuse_settings_that_change_the_problems(tiny, tmp_path, capsys):
    out, _ = tiny
    argv = ["--corpus", str(out), "--compile", "off", "--variant", "iterations=30", "--out", str(tmp_path)]
    assert bench_corpus.main(argv) == 0
    report = json.loads((tmp_path / "bench_corpus.json").read_text())
    rows = report["rows"]
    assert [(r["setting"], r["batch"]) for r in rows] == [("shipped", "state"), ("shipped", "all"),
                                                         ("iterations=30", "state"), ("iterations=30", "all")]
    ipopt = int(load_corpus(out / "cruise.pt")["ipopt_feasible"].sum())
    for row in rows:
        assert row["goals"] == 9 and row["states"] == 3
        assert row["both"] + row["ours_only"] + row["ipopt_only"] + row["neither"] == row["goals"]
        assert row["ours_feasible"] == row["both"] + row["ours_only"] and row["ipopt_feasible"] == ipopt == row["both"] + row["ipopt_only"]
        assert row["agreement"] == pytest.approx((row["both"] + row["neither"]) / row["goals"])
        assert row["ms_per_state"] > 0 and row["distance_mismatch"] < 1e-3  # recomputed distance = the result's
        if row["ours_feasible"]:  # the optimizer's obstacle_tolerance, beyond any depth the start already has
            assert row["max_obstacle_violation"] <= max(row["max_obstacle_violation_at_start"], 0.0) + 0.01 + 1e-6
    assert "| cruise | iterations=30 | state | 3 | 9 |" in capsys.readouterr().out
    bad = ["--corpus", str(out), "--compile", "off", "--no-shipped", "--variant", "ellipse_a=9.0", "--out", str(tmp_path / "bad")]
    assert bench_corpus.main(bad) == 2
    assert "optimizer.ellipse_a" in capsys.readouterr().err and not (tmp_path / "bad").exists()
