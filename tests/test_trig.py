"""mmpc.solver.trig: the polynomial sin/cos/atan2 of the compiled CPU path, against float64 references."""

import math

import pytest
import torch

from mmpc.solver import trig

# float32 rounding of values up to pi is 1.2e-7 (half an ulp of pi); the polynomials stay within
# about two ulps.
TOLERANCE = 3e-7


def test_sincos_matches_float64_over_the_documented_range():
    angle = torch.linspace(-1e4, 1e4, 400_001).float()
    sin, cos = trig.sincos(angle)
    reference = angle.double()
    assert (sin.double() - torch.sin(reference)).abs().max() < TOLERANCE
    assert (cos.double() - torch.cos(reference)).abs().max() < TOLERANCE


def test_sincos_exact_at_the_quadrant_boundaries():
    angle = torch.tensor([0.0, math.pi / 2, math.pi, -math.pi / 2, 3 * math.pi / 2, 2 * math.pi])
    sin, cos = trig.sincos(angle)
    torch.testing.assert_close(sin, torch.sin(angle), atol=TOLERANCE, rtol=0)
    torch.testing.assert_close(cos, torch.cos(angle), atol=TOLERANCE, rtol=0)


def test_atan2_matches_float64_over_every_scale_and_quadrant():
    generator = torch.Generator().manual_seed(0)
    size = 1_000_000
    scale = torch.exp(3.0 * torch.randn(2, size, generator=generator))
    y, x = (torch.randn(2, size, generator=generator) * scale).unbind()
    angle = trig.atan2(y, x)
    error = (angle.double() - torch.atan2(y.double(), x.double())).abs()
    assert error.max() < TOLERANCE
    assert (angle > 0).any() and (angle < -math.pi / 2).any()  # all four quadrants were drawn


@pytest.mark.parametrize(
    ("y", "x", "expected"),
    [
        (0.0, 0.0, 0.0),
        (0.0, 2.0, 0.0),
        (0.0, -2.0, math.pi),
        (3.0, 0.0, math.pi / 2),
        (-3.0, 0.0, -math.pi / 2),
        (1.0, 1.0, math.pi / 4),
        (-1.0, -1.0, -3 * math.pi / 4),
        (1e-30, -1e-30, 3 * math.pi / 4),
    ],
)
def test_atan2_on_axes_diagonals_and_the_origin(y, x, expected):
    angle = trig.atan2(torch.tensor([y]), torch.tensor([x]))
    assert angle.item() == pytest.approx(expected, abs=TOLERANCE)


def test_nan_propagates():
    nan = float("nan")
    assert trig.atan2(torch.tensor([nan, 1.0]), torch.tensor([1.0, nan])).isnan().all()
    sin, cos = trig.sincos(torch.tensor([nan]))
    assert sin.isnan().all() and cos.isnan().all()


def test_compiled_matches_eager():
    angle = torch.linspace(-7.0, 7.0, 4096)
    compiled = torch.compile(trig.sincos, fullgraph=True)
    for eager_value, compiled_value in zip(trig.sincos(angle), compiled(angle)):
        torch.testing.assert_close(compiled_value, eager_value, atol=TOLERANCE, rtol=0)
