"""``--seeds`` is counted before it is built: a range past :data:`MAX_SEEDS` is refused with how
many came and the limit, instead of a list of a billion ints (issue 44, item 10)."""

from __future__ import annotations

import argparse

import pytest

from mmpc.cli.arguments import MAX_SEEDS, seed_list
from mmpc.cli.main import build_parser


def test_seed_sets_past_the_bound_are_refused_with_the_count_and_the_limit():
    assert MAX_SEEDS == 1_000_000 and len(seed_list("0-999999")) == MAX_SEEDS
    with pytest.raises(argparse.ArgumentTypeError, match=r"'0-1000000' names 1,000,001 seeds; at most 1,000,000 are allowed"):
        seed_list("0-1000000")
    with pytest.raises(argparse.ArgumentTypeError, match="names 1,000,002 seeds"):  # repeats count
        seed_list("0-999999,5-6")


def test_a_huge_range_is_refused_without_building_it():
    with pytest.raises(argparse.ArgumentTypeError, match=r"names 1,000,000,000 seeds; at most 1,000,000"):
        seed_list("0-999999999")


def test_a_reversed_range_is_refused():
    with pytest.raises(argparse.ArgumentTypeError, match="low <= high"):
        seed_list("1,9-3")


@pytest.mark.parametrize("verb", ["evaluate", "drive"])
def test_the_command_line_refuses_too_many_seeds_as_a_usage_error(verb, capsys):
    with pytest.raises(SystemExit) as exit_:
        build_parser().parse_args([verb, "--sim", "batched", "--seeds", "0-1000000", "--duration", "1"])
    assert exit_.value.code == 2
    assert "names 1,000,001 seeds; at most 1,000,000 are allowed" in capsys.readouterr().err
