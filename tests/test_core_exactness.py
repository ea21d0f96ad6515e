"""The closed loop of design.closed_loop is exactly the error of design.estimator."""

import numpy as np
import pytest

from design.closed_loop import ClosedLoop
from design.estimator import NeighbourEstimate, PowerCache, estimator_step, role_from


@pytest.mark.parametrize("D", [np.zeros((3, 3), int), np.array([[0, 2, 0], [0, 0, 1], [3, 0, 0]])])
def test_error_recursion_matches_estimator(paper14, D):
    s = paper14
    n, N = s.n, s.N
    rng = np.random.default_rng(1)
    G = [0.3 * rng.normal(size=(n, 1)) for _ in range(N)]
    loop = ClosedLoop(s.A, s.W, D, s.measure, G)
    T = loop.taubar
    B, Gz = loop.noise_input(1.0, 1.0)
    P = PowerCache(s.A)
    K = 20
    x = np.zeros((K + 1, n))
    x[0] = rng.normal(size=n)
    nu = rng.normal(size=(K + 1, n))
    zeta = rng.normal(size=(K + 1, N))
    for k in range(K):
        x[k + 1] = s.A @ x[k] + nu[k]
    xh = np.zeros((K + 1, N, n))
    xh[0] = rng.normal(size=(N, n))
    for k in range(1, K + 1):
        for i in range(N):
            nbs = []
            for j in s.neighbours[i]:
                stamp = max(k - 1 - D[i, j], 0)
                nbs.append(NeighbourEstimate(s.W[i, j], k - stamp, xh[stamp, j]))
            y = x[k][list(s.measure[i])] + zeta[k, i]
            _, xh[k, i] = estimator_step(P, role_from(s, G, i), xh[k - 1, i], nbs, y)
    e = (x[:, None, :] - xh).reshape(K + 1, -1)
    for k in range(T + 2, K + 1):
        pred = sum(loop.F(r) @ e[k - 1 - r] for r in range(T + 1))
        pred = pred + sum(B[r] @ nu[k - 1 - r] for r in range(T + 1)) - Gz @ zeta[k]
        np.testing.assert_allclose(pred, e[k], rtol=1e-10, atol=1e-10 * np.abs(e[k]).max())
