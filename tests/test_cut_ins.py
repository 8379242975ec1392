"""MOBIL's safety criterion with the ego as an IDM follower (mmpc.verify.cut_ins): the bounds hold for
every car motion the assumptions allow, they are tight enough to matter, and the sim's MOBIL agrees."""

import math

import pytest
import torch

import mmpc
from mmpc.road import Road
from mmpc.verify import TrafficAssumptions, Verifier
from mmpc.verify.cut_ins import desired_gap, entry_floor, may_have_decided, safe_distance

ASSUMPTIONS = TrafficAssumptions()
FRAME = 0.2


def random_car_motion(generator, speed: float, frames: int):
    """(frames + 1,) speeds and along-road centre positions of a frame-stepped car (start at 0) whose
    acceleration each frame is drawn within [-max_deceleration, max_acceleration] (no reversing, the
    speed limit kept), turned now and then within the assumed heading, lateral speed and travel."""
    a = ASSUMPTIONS
    speeds, xs, lateral = [speed], [0.0], 0.0
    for _ in range(frames):
        acceleration = float(torch.empty(()).uniform_(-a.max_deceleration, a.max_acceleration, generator=generator))
        if float(torch.rand((), generator=generator)) < 0.3:  # long stretches of full braking or speeding
            acceleration = -a.max_deceleration if acceleration < 0 else a.max_acceleration
        turn = min(a.max_heading, math.asin(min(1.0, a.lateral_speed / max(speeds[-1], 1e-9))))
        heading = turn * (float(torch.rand((), generator=generator)) < 0.3)
        step = speeds[-1] * FRAME
        if lateral + step * math.sin(heading) > a.lateral_travel:
            heading = 0.0
        lateral += step * math.sin(heading)
        xs.append(xs[-1] + step * math.cos(heading))
        speeds.append(min(max(speeds[-1] + acceleration * FRAME, 0.0), max(speed, a.speed_limit)))
    return torch.tensor(speeds, dtype=torch.float64), torch.tensor(xs, dtype=torch.float64)


def braking_ego(speed: float, frames: int, braking: float = 5.0, first: float = -5.0):
    """(frames,) x and speed of an ego that applies ``first`` one frame, then brakes to rest."""
    speeds = [speed]
    xs = [0.0]
    for frame in range(frames - 1):
        xs.append(xs[-1] + speeds[-1] * FRAME)
        speeds.append(max(speeds[-1] + (first if frame == 0 else -braking) * FRAME, 0.0))
    return torch.tensor(xs, dtype=torch.float64), torch.tensor(speeds, dtype=torch.float64)


@pytest.mark.parametrize("seed", range(8))
def test_a_car_that_decides_to_cut_in_stays_past_the_entry_floor(seed):
    """Cars in random motion, each deciding at a random pose where the criterion lets it (the ego
    following it would brake at most 2 m/s^2): from then on its footprint's rear never lies behind
    the floor of the ego's path (the ego's first command random, then braking)."""
    generator = torch.Generator().manual_seed(seed)
    frames = 50
    times = torch.arange(frames + 1, dtype=torch.float64) * FRAME
    checked = 0
    for _ in range(80):
        ego_speed = float(torch.empty(()).uniform_(2.0, 30.0, generator=generator))
        ego_x, ego_v = braking_ego(ego_speed, frames, first=float(torch.empty(()).uniform_(-5.0, 5.0, generator=generator)))
        car_speed = float(torch.empty(()).uniform_(0.0, 30.0, generator=generator))
        gap = float(torch.empty(()).uniform_(0.0, 60.0, generator=generator))
        speeds, xs = random_car_motion(generator, car_speed, frames)
        centres = gap + xs[:frames]
        floor = entry_floor(ego_x[None], ego_v[None], torch.tensor([[gap, 8.0, car_speed, 0.0]], dtype=torch.float64),
                            times, ASSUMPTIONS)[0]
        needed = safe_distance(ASSUMPTIONS, desired_gap(ASSUMPTIONS, ego_v, speeds[:frames]).abs(), ego_v)
        admits = (centres - ego_x > 0) & (centres - ego_x >= needed)
        if not bool(admits.any()):
            continue
        choices = admits.nonzero()[:, 0]
        decided = int(choices[torch.randint(choices.numel(), (), generator=generator)])
        rear = centres[decided:] - ASSUMPTIONS.half_length
        assert bool((rear >= floor[decided:] - 1e-9).all()), (seed, ego_speed, car_speed, gap, decided)
        checked += 1
    assert checked >= 20  # the draw reaches the criterion often enough to test it


def test_the_entry_floor_is_tight_enough_to_let_the_ego_brake_behind_a_slower_car():
    """An ego at 20 m/s braking at 5 behind-beside a car at 8 m/s 20 m ahead: the car may cut in once
    the ego has slowed, yet never inside the ego's stopping path (a floor that dropped to the ego would
    refuse every such step)."""
    ego_x, ego_v = braking_ego(20.0, 45)
    times = torch.arange(46, dtype=torch.float64) * FRAME
    floor = entry_floor(ego_x[None], ego_v[None], torch.tensor([[20.0, 8.0, 8.0, 0.0]], dtype=torch.float64), times,
                        ASSUMPTIONS)[0]
    front = ego_x + 2.5
    assert bool((floor > front).all())


@pytest.mark.parametrize("seed", range(3))
def test_a_decision_taken_within_the_lag_is_counted(seed):
    """States a decision-lag ago drawn backwards from now within the bounds: wherever the criterion
    held then, may_have_decided says so now."""
    generator = torch.Generator().manual_seed(seed)
    a = ASSUMPTIONS
    lag = a.decision_lag
    for _ in range(300):
        ego_then = float(torch.empty(()).uniform_(0.0, 30.0, generator=generator))
        car_then = float(torch.empty(()).uniform_(0.0, 30.0, generator=generator))
        gap_then = float(torch.empty(()).uniform_(0.0, 80.0, generator=generator))
        ego_acc = float(torch.empty(()).uniform_(-a.ego_acceleration, a.ego_acceleration, generator=generator))
        car_acc = float(torch.empty(()).uniform_(-a.max_deceleration, a.max_acceleration, generator=generator))
        ego_now, car_now = max(ego_then + ego_acc * lag, 0.0), max(car_then + car_acc * lag, 0.0)
        ego_moved = (ego_then + ego_now) / 2 * lag
        car_moved = (car_then + car_now) / 2 * lag
        needed = safe_distance(a, desired_gap(a, torch.tensor(ego_then), torch.tensor(car_then)).abs(), torch.tensor(ego_then))
        if not gap_then >= float(needed):
            continue
        ego = mmpc.ego_state(0.0, 4.0, 0.0, ego_now).reshape(1, 6).double()
        car = torch.tensor([[[gap_then + car_moved - ego_moved, 8.0, car_now, 0.0]]], dtype=torch.float64)
        assert bool(may_have_decided(ego, car, a)[0, 0]), (ego_then, car_then, gap_then, ego_acc, car_acc)


def check(ego, cars, cut_in="follower"):
    verifier = Verifier(Road(4, 4.0), assumptions=TrafficAssumptions(cut_in=cut_in))
    vehicles = torch.tensor([cars], dtype=torch.float32)
    verdict = verifier.check(ego.reshape(1, 6), vehicles, torch.ones(vehicles.shape[:2], dtype=torch.bool),
                             torch.zeros(1, 1), torch.zeros(1, 1))
    return bool(verdict.verified[0, 0])


def test_the_rules_differ_where_a_car_may_cut_in_ahead_of_the_ego():
    slow_ego, fast_ego = mmpc.ego_state(0.0, 4.0, 0.0, 10.0), mmpc.ego_state(0.0, 4.0, 0.0, 25.0)
    faster_beside = [[4.0, 8.0, 25.0, 0.0]]  # the ego behind it would barely brake: it may cut in at once
    assert not check(slow_ego, faster_beside)
    assert check(slow_ego, faster_beside, cut_in="highway-env")
    slower_ahead = [[20.0, 8.0, 15.0, 0.0]]  # it may cut in once the braking ego has fallen back enough
    assert not check(fast_ego, slower_ahead)
    assert check(fast_ego, slower_ahead, cut_in="highway-env")
    assert check(fast_ego, [[60.0, 8.0, 15.0, 0.0]])  # far enough for the ego's whole stop
    level = [[5.0, 8.0, 20.0, 0.0]]  # level at the same speed: it falls back into the ego's path only behind it
    ego = mmpc.ego_state(0.0, 4.0, 0.0, 20.0)
    assert check(ego, level) and check(ego, level, cut_in="highway-env") and not check(ego, level, cut_in="any")


def test_an_unknown_rule_is_refused():
    with pytest.raises(ValueError, match="cut_in"):
        TrafficAssumptions(cut_in="mobil")


@pytest.mark.parametrize("size", [7, 5000])  # below and above CUMMIN_MAX_VALUES along a middle dimension
def test_the_running_minimum_is_cummins_on_either_side_of_its_size_switch(size):
    from mmpc.verify.cut_ins import CUMMIN_MAX_VALUES, running_min

    values = torch.randn(3, 61, size, dtype=torch.float64, generator=torch.Generator().manual_seed(size))
    values[0, 5, :3] = float("nan")
    assert (values.numel() > CUMMIN_MAX_VALUES) == (size == 5000)
    torch.testing.assert_close(running_min(values, dim=1), torch.cummin(values, dim=1).values, equal_nan=True,
                               rtol=0, atol=0)
