"""Constant matrices of the alternating minimisation, built once in float64.

Every matrix below is independent of the batch, the obstacle positions and the goals; the
iterations only multiply them with right-hand sides.

Per axis (x or y) with M present obstacles the position QP of iteration k is::

    min_c 1/2 c^T Q c - lambda^T c + rho_k/2 ||F_M c - g||^2   s.t.  A c = b
    F_M = [P; ...; P (M times); Pddot; Pdot]

Its KKT solution is ``c = Kcc (rho_k F_M^T g + lambda) + Kcb b`` with (Kcc, Kcb) blocks of the
inverse KKT matrix. Writing ``F_M^T g = F_M^T F_M c_prev - u`` with ``u = F^T (F c_prev - g)``
(the residual already mapped back to coefficient space) gives a product of one constant matrix
with the stacked vector ``[c_prev, u, lambda, b]`` — :func:`position_operators` returns that
matrix for every iteration and every obstacle count 0 ... M_max. The heading QP is the same with
``F = P`` and target ``atan2(ydot, xdot)``: ``[psi_target, lambda_psi, b_psi]`` times
:func:`heading_operators`.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from mmpc.basis import Basis
from mmpc.config import OptimizerConfig


class Operators(NamedTuple):
    """All constant matrices, float64 on the CPU. K coefficients, N samples, I iterations.

    Shapes:
        samples: (K, 3N) maps coefficients to [position, acceleration, velocity] samples:
            ``c @ samples`` for c of shape (..., K).
        gather: (3N, K) = samples^T, maps stacked [position, acceleration, velocity] residuals
            back to coefficient space.
        position: (I, M_max + 1, 3K + n_eq, K) right-multiplies ``[c_prev, u, lambda, b]``.
        position_init: (n_eq, K) right-multiplies ``b`` for the smoothest trajectory meeting the
            boundary conditions (the cold start).
        heading: (I, N + K + 4, K) right-multiplies ``[psi_target, lambda_psi, b_psi]``.
        heading_basis: (K, N) ``c_psi @ heading_basis`` gives psi samples.
        heading_gather: (N, K) = heading_basis^T, maps heading residuals to coefficient space.
        heading_rate_basis: (K, N) gives psidot samples.
        rho: (I,) penalty weight of every iteration.
    """

    samples: torch.Tensor
    gather: torch.Tensor
    position: torch.Tensor
    position_init: torch.Tensor
    heading: torch.Tensor
    heading_basis: torch.Tensor
    heading_gather: torch.Tensor
    heading_rate_basis: torch.Tensor
    rho: torch.Tensor


def position_equality_matrix(basis: Basis, start_acceleration: bool) -> torch.Tensor:
    """Rows of A for one axis: start position, start velocity, [start acceleration,] end position."""
    rows = [basis.P[0], basis.Pdot[0]]
    if start_acceleration:
        rows.append(basis.Pddot[0])
    rows.append(basis.P[-1])
    return torch.stack(rows)


def heading_equality_matrix(basis: Basis) -> torch.Tensor:
    """Rows of A_psi: start heading, start rate, end heading, end rate."""
    return torch.stack([basis.P[0], basis.Pdot[0], basis.P[-1], basis.Pdot[-1]])


def _kkt_blocks(hessian: torch.Tensor, equality: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(Kcc, Kcb) blocks of the inverse of [[H, A^T], [A, 0]]."""
    k, n_eq = hessian.shape[0], equality.shape[0]
    kkt = torch.zeros(k + n_eq, k + n_eq, dtype=torch.float64)
    kkt[:k, :k] = hessian
    kkt[:k, k:] = equality.T
    kkt[k:, :k] = equality
    inverse = torch.linalg.inv(kkt)
    return inverse[:k, :k], inverse[:k, k:]


def build_operators(basis: Basis, config: OptimizerConfig) -> Operators:
    """Build every constant matrix of the solver for ``config`` (float64)."""
    P, Pd, Pdd = basis.P, basis.Pdot, basis.Pddot
    rho = torch.tensor(config.rho_schedule(), dtype=torch.float64)
    smooth_xy = config.weight_xy * Pdd.T @ Pdd
    smooth_psi = config.weight_psi * Pdd.T @ Pdd
    gram_position = P.T @ P
    gram_motion = Pdd.T @ Pdd + Pd.T @ Pd

    equality = position_equality_matrix(basis, config.start_acceleration)
    position = []
    for rho_k in rho.tolist():
        per_count = []
        for m in range(config.max_obstacles + 1):
            gram = m * gram_position + gram_motion
            kcc, kcb = _kkt_blocks(smooth_xy + rho_k * gram, equality)
            # c_new = [c_prev, u, lambda, b] @ W with W the transpose of [rho Kcc G, -rho Kcc, Kcc, Kcb].
            stacked = torch.cat([rho_k * kcc @ gram, -rho_k * kcc, kcc, kcb], dim=1)
            per_count.append(stacked.T)
        position.append(torch.stack(per_count))

    _, kcb_init = _kkt_blocks(smooth_xy, equality)

    heading_equality = heading_equality_matrix(basis)
    heading = []
    for rho_k in rho.tolist():
        kcc, kcb = _kkt_blocks(smooth_psi + rho_k * gram_position, heading_equality)
        heading.append(torch.cat([rho_k * kcc @ P.T, kcc, kcb], dim=1).T)

    samples = torch.cat([P, Pdd, Pd], dim=0).T.contiguous()
    return Operators(
        samples=samples,
        gather=samples.T.contiguous(),
        position=torch.stack(position),
        position_init=kcb_init.T.contiguous(),
        heading=torch.stack(heading),
        heading_basis=P.T.contiguous(),
        heading_gather=P.contiguous(),
        heading_rate_basis=Pd.T.contiguous(),
        rho=rho,
    )
