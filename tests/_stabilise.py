"""A small local routine that finds a stabilising gain for tests.

Gradient descent on the exact spectral radius of the delayed closed loop
(:class:`design.closed_loop.ClosedLoop`), with the eigenvalue sensitivity
``d lambda = u^H dM v / (u^H v)``. Only the first block row of the companion depends on
the gains: rows of agent i are ``L_i (W_r[i] (x) A^(r+1))`` with ``L_i = I - G_i H_i``,
so ``dM`` there is ``-dG_i H_i (W_r[i] (x) A^(r+1))``.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg as sla

from design.closed_loop import ClosedLoop


def _radius_and_gradient(A, W, D, measure, G):
    loop = ClosedLoop(A, W, D, measure, G)
    M = loop.companion(sparse=False) if loop.taubar else loop.F(0)
    vals, vl, vr = sla.eig(M, left=True, right=True)
    m = int(np.argmax(np.abs(vals)))
    lam, u, v = vals[m], vl[:, m], vr[:, m]
    c = np.vdot(u, v)
    n, N = loop.n, loop.N
    nN = n * N
    grads = []
    for i in range(N):
        meas = list(loop.measure[i])
        Rv = np.zeros(len(meas), dtype=complex)   # H_i sum_r (W_r[i] (x) A^(r+1)) v_r
        for j in range(N):
            w = loop.W[i, j]
            if w > 0:
                r = int(loop.delays[i, j])
                vj = v[r * nN + j * n: r * nN + (j + 1) * n]
                Rv += w * (loop.A_powers[r + 1][meas] @ vj)
        ui = u[i * n:(i + 1) * n]
        dlam = -np.outer(np.conj(ui), Rv) / np.conj(c)   # d lambda / d G_i[a, b]
        grads.append(np.real(np.conj(lam) * dlam) / abs(lam))
    return abs(lam), grads


def stabilising_gain(scenario, delays=None, iters=400, step=0.05, target=0.9, seed=0):
    """A gain with exact radius < 1 for ``scenario`` and ``delays`` (default its own).

    Returns ``(G, rho)``. Stops once the radius is below ``target``.
    """
    A, W = scenario.A, scenario.W
    D = scenario.delays if delays is None else np.asarray(delays)
    rng = np.random.default_rng(seed)
    G = [0.1 * rng.standard_normal((scenario.n, len(m))) for m in scenario.measure]
    rho, grad = _radius_and_gradient(A, W, D, scenario.measure, G)
    for _ in range(iters):
        if rho < target:
            break
        norm = np.sqrt(sum(float(np.sum(g * g)) for g in grad)) or 1.0
        t = step
        while t > 1e-6:
            trial = [g - t * d / norm for g, d in zip(G, grad)]
            r2, g2 = _radius_and_gradient(A, W, D, scenario.measure, trial)
            if r2 < rho:
                G, rho, grad = trial, r2, g2
                break
            t /= 2
        else:
            G = [g + 1e-3 * rng.standard_normal(g.shape) for g in G]
            rho, grad = _radius_and_gradient(A, W, D, scenario.measure, G)
    return G, rho
