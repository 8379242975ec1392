import pytest
import torch

from mmpc.solver.basis import bernstein_basis


def test_partition_of_unity_and_endpoints():
    basis = bernstein_basis(10, 100, 8.0)
    assert basis.P.shape == (100, 11)
    torch.testing.assert_close(basis.P.sum(dim=1), torch.ones(100, dtype=torch.float64))
    torch.testing.assert_close(basis.Pdot.sum(dim=1), torch.zeros(100, dtype=torch.float64))
    assert basis.P[0, 0] == 1.0 and basis.P[-1, -1] == 1.0
    assert basis.times[0] == 0.0 and basis.times[-1] == 8.0


def test_derivatives_match_finite_differences():
    fine = bernstein_basis(10, 4001, 8.0)
    coeffs = torch.linspace(-3.0, 5.0, 11, dtype=torch.float64) ** 2
    x, xd, xdd = fine.P @ coeffs, fine.Pdot @ coeffs, fine.Pddot @ coeffs
    dt = fine.times[1] - fine.times[0]
    torch.testing.assert_close(torch.gradient(x, spacing=dt.item())[0][1:-1], xd[1:-1], atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(torch.gradient(xd, spacing=dt.item())[0][1:-1], xdd[1:-1], atol=1e-3, rtol=1e-3)


def test_polynomial_is_reproduced_exactly():
    # t^2 in Bernstein form on [0, T]: derivative matrices give 2t and 2.
    basis = bernstein_basis(5, 50, 4.0)
    coeffs = torch.linalg.lstsq(basis.P, basis.times**2).solution
    torch.testing.assert_close(basis.Pdot @ coeffs, 2 * basis.times, atol=1e-9, rtol=1e-9)
    torch.testing.assert_close(basis.Pddot @ coeffs, torch.full((50,), 2.0, dtype=torch.float64), atol=1e-8, rtol=1e-8)


@pytest.mark.parametrize("kwargs", [dict(order=2, num_steps=10, horizon=1.0), dict(order=5, num_steps=1, horizon=1.0), dict(order=5, num_steps=10, horizon=0.0)])
def test_rejects_bad_arguments(kwargs):
    with pytest.raises(ValueError):
        bernstein_basis(**kwargs)
