"""sin, cos and atan2 as short polynomials, for the compiled CPU iterations.

The vectorised library calls behind ``torch.cos``, ``torch.sin`` and ``torch.atan2`` handle any
float32 argument to about 1 ulp; on the CPU they cost more than the rest of the elementwise
work of an iteration together. The heading of a trajectory stays within a few radians, where a
range reduction by pi/2 (cos, sin) or to |u| <= tan(pi/8) (atan2) followed by a truncated Taylor
series is exact to float32 rounding, and every step is a multiply, add or select that a
compiler fuses into the surrounding loop. Both functions are plain tensor code: eager they are
slower than the library calls (many small kernels), compiled they are several times faster.

Accuracy (float32, against float64 references; ``tests/test_trig.py``):
    sincos: absolute error < 3e-7 for |x| <= 1e4 rad; beyond that the reduction loses bits.
    atan2: absolute error < 3e-7 rad for every finite (y, x); atan2(0, 0) = 0; NaN propagates.
"""

from __future__ import annotations

import math

import torch

# pi / 2 split in three parts whose leading ones have few significant bits, so that
# k * part is exact in float32 for |k| < 2^15 (Cody and Waite's reduction).
_HALF_PI_PARTS = (1.5703125, 4.837512969970703125e-4, 7.54978995489188216e-8)
# Taylor coefficients of sin r / r and cos r in r^2; on |r| <= pi/4 the first omitted terms
# are below 2e-9.
_SIN = (1.0, -1.0 / 6.0, 1.0 / 120.0, -1.0 / 5040.0, 1.0 / 362880.0)
_COS = (1.0, -0.5, 1.0 / 24.0, -1.0 / 720.0, 1.0 / 40320.0, -1.0 / 3628800.0)
# Taylor coefficients of atan u / u in u^2 (1, -1/3, 1/5, ...); on |u| <= tan(pi/8) the first
# omitted term is below 2e-8.
_ATAN = tuple((-1.0) ** i / (2 * i + 1) for i in range(8))
_TAN_PI_8 = math.tan(math.pi / 8)
_TAN_3PI_8 = math.tan(3 * math.pi / 8)


def _polynomial(square: torch.Tensor, coefficients: tuple[float, ...]) -> torch.Tensor:
    """sum_i coefficients[i] * square^i by Horner's rule."""
    value = torch.full_like(square, coefficients[-1])
    for coefficient in reversed(coefficients[:-1]):
        value = value * square + coefficient
    return value


def sincos(angle: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(sin angle, cos angle), elementwise; ``angle`` in radians, any shape.

    ``angle = k pi/2 + r`` with integer k and |r| <= pi/4; the quadrant k mod 4 swaps and
    negates the series of sin r and cos r.
    """
    quadrants = torch.round(angle * (2.0 / math.pi))
    reduced = angle
    for part in _HALF_PI_PARTS:
        reduced = reduced - quadrants * part
    square = reduced * reduced
    sin_reduced = reduced * _polynomial(square, _SIN)
    cos_reduced = _polynomial(square, _COS)
    quadrant = quadrants - 4.0 * torch.floor(quadrants * 0.25)  # k mod 4 in {0, 1, 2, 3}
    odd = (quadrant == 1.0) | (quadrant == 3.0)
    sin = torch.where(odd, cos_reduced, sin_reduced)
    cos = torch.where(odd, sin_reduced, cos_reduced)
    sin = torch.where(quadrant >= 2.0, -sin, sin)
    cos = torch.where((quadrant == 1.0) | (quadrant == 2.0), -cos, cos)
    return sin, cos


def atan2(y: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """The angle of the vector (x, y) in (-pi, pi], elementwise, like :func:`torch.atan2`.

    The angle of (|x|, |y|) is taken from one of three sectors of the first quadrant, each
    rotated to |u| <= tan(pi/8) with a single division, then reflected into the quadrant of
    (x, y). Signed zeros are not distinguished: atan2(+-0, x < 0) = pi, atan2(0, +-0) = 0.
    """
    ax, ay = x.abs(), y.abs()
    low = ay <= ax * _TAN_PI_8  # angle < pi/8: u = ay / ax
    high = ay > ax * _TAN_3PI_8  # angle > 3 pi/8: u = -ax / ay, from pi/2
    numerator = torch.where(low, ay, torch.where(high, -ax, ay - ax))
    denominator = torch.where(low, ax, torch.where(high, ay, ay + ax))
    # Only (0, 0) has a zero denominator (in the low sector, with a zero numerator).
    ratio = numerator / torch.where(denominator > 0.0, denominator, torch.ones_like(denominator))
    base = torch.where(low, 0.0, torch.where(high, math.pi / 2, math.pi / 4))
    angle = base + ratio * _polynomial(ratio * ratio, _ATAN)
    angle = torch.where(x < 0.0, math.pi - angle, angle)
    return torch.where(y < 0.0, -angle, angle)
