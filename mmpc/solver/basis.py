"""Bernstein polynomial basis on a fixed horizon.

A trajectory coordinate sampled at ``N`` instants is ``P @ c`` with ``c`` the ``K = order + 1``
Bernstein coefficients. Time is normalised, ``tau = t / t_f`` in ``[0, 1]``, so the derivative
matrices carry the chain-rule factors ``1 / t_f`` and ``1 / t_f**2``.
"""

from __future__ import annotations

from math import comb
from typing import NamedTuple

import torch


class Basis(NamedTuple):
    """Basis matrices of one horizon (all float64, CPU).

    Shapes:
        times: (N,) sample instants [s], ``0 ... t_f``.
        P: (N, K) positions.
        Pdot: (N, K) first derivatives [1/s].
        Pddot: (N, K) second derivatives [1/s^2].
    """

    times: torch.Tensor
    P: torch.Tensor
    Pdot: torch.Tensor
    Pddot: torch.Tensor


def _bernstein(order: int, tau: torch.Tensor) -> torch.Tensor:
    """Bernstein polynomials ``B_{i,order}(tau)``, shape (len(tau), order + 1); order 0 gives ones."""
    if order < 0:
        return torch.zeros(tau.shape[0], 0, dtype=tau.dtype)
    i = torch.arange(order + 1, dtype=tau.dtype)
    binom = torch.tensor([comb(order, k) for k in range(order + 1)], dtype=tau.dtype)
    t = tau[:, None]
    return binom * t**i * (1.0 - t) ** (order - i)


def _derivative_of_bernstein(order: int, values_lower: torch.Tensor) -> torch.Tensor:
    """d/dtau of the order-``order`` basis from the order-``order-1`` basis values.

    Uses ``B'_{i,n} = n (B_{i-1,n-1} - B_{i,n-1})`` with out-of-range terms equal to zero.
    """
    n_rows = values_lower.shape[0]
    zeros = torch.zeros(n_rows, 1, dtype=values_lower.dtype)
    left = torch.cat([zeros, values_lower], dim=1)
    right = torch.cat([values_lower, zeros], dim=1)
    return order * (left - right)


def bernstein_basis(order: int, num_steps: int, horizon: float) -> Basis:
    """Bernstein basis of ``order`` sampled at ``num_steps`` evenly spaced instants of ``[0, horizon]``.

    Args:
        order: polynomial order n (K = n + 1 coefficients); at least 3 so that a trajectory can
            meet position, velocity and acceleration conditions at the start and a position at the end.
        num_steps: number of samples N, at least 2; the first is t = 0, the last t = horizon.
        horizon: t_f [s], positive.

    Returns:
        A :class:`Basis` in float64.

    Example:
        >>> b = bernstein_basis(10, 100, 8.0)
        >>> b.P.shape, float(b.P.sum(1).max())
        (torch.Size([100, 11]), 1.0)
    """
    if order < 3:
        raise ValueError(f"`order` must be >= 3; got {order}")
    if num_steps < 2:
        raise ValueError(f"`num_steps` must be >= 2; got {num_steps}")
    if not horizon > 0:
        raise ValueError(f"`horizon` must be > 0 s; got {horizon}")
    tau = torch.linspace(0.0, 1.0, num_steps, dtype=torch.float64)
    P = _bernstein(order, tau)
    dP = _derivative_of_bernstein(order, _bernstein(order - 1, tau))
    lower_first = _derivative_of_bernstein(order - 1, _bernstein(order - 2, tau))
    ddP = _derivative_of_bernstein(order, lower_first)
    return Basis(times=tau * horizon, P=P, Pdot=dP / horizon, Pddot=ddP / horizon**2)


def bernstein_shift(order: int, num_steps: int, horizon: float, dt: float) -> torch.Tensor:
    """(K, K) float64 ``S`` with ``P S c`` ~ the trajectory of ``c`` delayed by ``dt`` [s]
    (``p(t + dt)``; past ``horizon`` extrapolated), in the least-squares sense over the
    ``num_steps`` sample instants: the next control step's start for a plan.

    Example:
        >>> bool(torch.allclose(bernstein_shift(10, 100, 8.0, 0.0), torch.eye(11, dtype=torch.float64)))
        True
    """
    tau = torch.linspace(0.0, 1.0, num_steps, dtype=torch.float64)
    return torch.linalg.lstsq(_bernstein(order, tau), _bernstein(order, tau + dt / horizon)).solution
