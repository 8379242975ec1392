"""Constant matrices of the alternating minimisation, built once in float64.

Every matrix below is independent of the batch, the obstacle positions and the goals; the
iterations only multiply them with right-hand sides.

Per axis (x or y) with M present obstacles the position QP of iteration k is::

    min_c 1/2 c^T Q c - lambda^T c + rho_k/2 ||F_M c - g||^2   s.t.  A c = b
    F_M = [P; ...; P (M times); Pddot; Pdot]

Its KKT solution is ``c = Kcc (rho_k F_M^T g + lambda) + Kcb b`` with (Kcc, Kcb) blocks of the
inverse KKT matrix. Writing ``F_M^T g = F_M^T F_M c_prev - u`` with ``u = F^T (F c_prev - g)``
(the residual already mapped back to coefficient space) makes the update one constant matrix
times the stacked vector ``[c_prev; u; lambda; b]`` (with the penalty weights folded in, see
:class:`Operators`); :func:`build_operators` returns that matrix
for every iteration and every obstacle count 0 ... M_max, so that absent obstacles change
nothing. The heading QP is the same with ``F = P`` and target ``atan2(ydot, xdot)``: one matrix
times ``[psi_target; lambda_psi; b_psi]``.

The lateral axis may add lane keeping, ``w/2 sum_t s(t) (y(t) - y_goal)^2``
(:attr:`mmpc.OptimizerConfig.lane_weight`): ``w P^T S P`` joins its Hessian and, as ``y_goal`` is
the end-position row of ``b``, its linear term ``w P^T S 1 y_goal`` folds into the ``b`` block.
The y axis then has matrices of its own, and the iterations stay one constant matrix per axis.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from mmpc.solver.basis import Basis
from mmpc.solver.config import OptimizerConfig


class Operators(NamedTuple):
    """All constant matrices, float64 on the CPU. K coefficients, N samples, I iterations.

    The solver keeps the batch in the *last* (column) dimension, so every operator multiplies
    from the left.

    The penalty weights are folded into the matrices, so the iterations never multiply by a
    scalar: the multiplier step of iteration k is ``lambda -= gather[k] @ R`` with
    ``gather[k] = rho_k [-P^T, Pddot^T, Pdot^T]`` applied to the stacked residual
    ``R = [obstacle push; acceleration residual; velocity residual]`` (the push is projection
    minus point, hence the minus sign), and the position QP of iteration k+1 reuses that
    product ``rho_k u``.

    Shapes:
        samples: (3N, K) maps coefficients to stacked [position; acceleration; velocity] samples.
        gather: (I, K, 3N) ``rho_k F^T`` on the stacked residual, per iteration.
        position: (I, M_max + 1, 2, K, 3K + n_eq) left-multiplies ``[c_prev; rho_{k-1} u; lambda; b]``
            of the x axis (index 0) and the y axis (1) (rho_{-1} = rho_0: the cold start's
            residual is mapped with ``gather[0]``); the two are equal without lane keeping.
        position_init: (2, K, n_eq) left-multiplies ``b`` for the smoothest trajectory meeting the
            boundary conditions (and keeping the lane, y axis), the cold start.
        heading: (I, K, N + K + 4) left-multiplies ``[psi_target; lambda_psi; b_psi]``.
        heading_gather: (I, K, N) ``rho_k P^T``: ``lambda_psi += heading_gather[k] @ (psi_target - psi)``.
        heading_basis: (N, K) P, psi samples from heading coefficients.
        heading_rate_basis: (N, K) Pdot, psidot samples.
    """

    samples: torch.Tensor
    gather: torch.Tensor
    position: torch.Tensor
    position_init: torch.Tensor
    heading: torch.Tensor
    heading_gather: torch.Tensor
    heading_basis: torch.Tensor
    heading_rate_basis: torch.Tensor


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


def lane_keeping_profile(times: torch.Tensor, settle_time: float) -> torch.Tensor:
    """(N,) weight s(t) of the lane-keeping term at ``times`` [s]: ``(t / settle_time)^2`` up to
    ``settle_time``, 1 after; 0 at the start, where the ego's lateral position is given."""
    return (times / settle_time).clamp(max=1.0) ** 2


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
    rho = config.rho_schedule()
    smooth = config.weight_xy * Pdd.T @ Pdd
    gram_position = P.T @ P
    gram_motion = Pdd.T @ Pdd + Pd.T @ Pd
    equality = position_equality_matrix(basis, config.start_acceleration)
    # Lane keeping on y: w P^T S P in the Hessian, w P^T S 1 y_goal (y_goal = b's last row) linear.
    lane = config.lane_weight * lane_keeping_profile(basis.times, config.lane_settle_time)
    end_row = torch.zeros(1, equality.shape[0], dtype=torch.float64)
    end_row[0, -1] = 1.0
    axes = [(smooth, torch.zeros(P.shape[1], equality.shape[0], dtype=torch.float64)),
            (smooth + P.T @ (lane[:, None] * P), (P.T @ lane)[:, None] @ end_row)]  # (Hessian, linear per b) of x, y

    def solve(hessian: torch.Tensor, linear: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        kcc, kcb = _kkt_blocks(hessian, equality)
        return kcc, kcb + kcc @ linear

    position = []
    for k, rho_k in enumerate(rho):
        rho_previous = rho[k - 1] if k > 0 else rho[0]
        per_count = []
        for m in range(config.max_obstacles + 1):
            gram = m * gram_position + gram_motion
            per_axis = []
            for hessian, linear in axes:
                kcc, kcb = solve(hessian + rho_k * gram, linear)
                # c = rho_k Kcc (G c_prev - u) + Kcc lambda + Kcb b, since F^T g = G c_prev - u.
                per_axis.append(torch.cat([rho_k * kcc @ gram, -(rho_k / rho_previous) * kcc, kcc, kcb], dim=1))
            per_count.append(torch.stack(per_axis))
        position.append(torch.stack(per_count))
    position_init = torch.stack([solve(hessian, linear)[1] for hessian, linear in axes])

    smooth_psi = config.weight_psi * Pdd.T @ Pdd
    heading_equality = heading_equality_matrix(basis)
    heading = []
    for rho_k in rho:
        kcc, kcb = _kkt_blocks(smooth_psi + rho_k * gram_position, heading_equality)
        heading.append(torch.cat([rho_k * kcc @ P.T, kcc, kcb], dim=1))

    rho_column = torch.tensor(rho, dtype=torch.float64)[:, None, None]
    gather = torch.cat([-P, Pdd, Pd], dim=0).T
    return Operators(
        samples=torch.cat([P, Pdd, Pd], dim=0).contiguous(),
        gather=(rho_column * gather).contiguous(),
        position=torch.stack(position),
        position_init=position_init.contiguous(),
        heading=torch.stack(heading),
        heading_gather=(rho_column * P.T).contiguous(),
        heading_basis=P.contiguous(),
        heading_rate_basis=Pd.contiguous(),
    )
