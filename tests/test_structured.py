"""The loop applied through its sparse and low-rank factors (design.structured) agrees with
the dense loop: products, radius and steady MSE, with heterogeneous delays."""

import numpy as np
import pytest

import design.closed_loop as cl
import design.gradient as gr
from design.closed_loop import ClosedLoop
from design.generate import communities_scenario
from design.scenario import load_scenario, scenario_from_dict
from design.structured import LoopOperator, impulse_mse


def _communities(N, seed=0):
    return scenario_from_dict(communities_scenario(N, seed=seed))


def _delayed_loop(s, seed=1, gain=0.6):
    """Heterogeneous delays 0-3 on W's links and seeded gains."""
    rng = np.random.default_rng(seed)
    D = np.where(s.W > 0, rng.integers(0, 4, s.W.shape), 0)
    np.fill_diagonal(D, 0)
    G = [gain * np.eye(s.n)[:, list(m)] + 0.05 * rng.standard_normal((s.n, len(m)))
         for m in s.measure]
    return ClosedLoop(s.A, s.W, D, s.measure, G)


def test_the_products_are_the_dense_companions_and_the_noise_systems():
    loop = _delayed_loop(_communities(4))
    op = LoopOperator(loop)
    M = loop.companion(sparse=False)
    X = np.random.default_rng(2).standard_normal((loop.order, 3))
    np.testing.assert_allclose(op.matvec(X), M @ X, rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(op.rmatvec(X), M.T @ X, rtol=1e-13, atol=1e-13)
    Ma, B, _ = loop.noise_state_space(0.3, 0.7)
    Y = np.random.default_rng(3).standard_normal((Ma.shape[0], 2))
    np.testing.assert_allclose(op.aug_matvec(Y), Ma @ Y, rtol=1e-13, atol=1e-13)
    Bs = op.noise_input(0.3, 0.7)
    np.testing.assert_allclose(Bs @ Bs.T, B @ B.T, rtol=1e-13, atol=1e-13)


@pytest.mark.parametrize("delays", ["none", "heterogeneous"])
def test_radius_and_mse_agree_with_the_dense_solves(monkeypatch, delays):
    s = _communities(8 if delays == "heterogeneous" else 16)
    loop = _delayed_loop(s) if delays == "heterogeneous" else ClosedLoop(
        s.A, s.W, s.delays, s.measure, [0.6 * np.eye(s.n)[:, list(m)] for m in s.measure])
    q, r = s.process_noise, s.measurement_noise
    op = LoopOperator(loop)
    rho_dense = float(np.max(np.abs(np.linalg.eigvals(loop.companion(sparse=False)))))
    rho = cl.spectral_radius(op.linear_operator(), dense=lambda: loop.companion(sparse=False))
    assert rho == pytest.approx(rho_dense, rel=1e-10)
    Ma, B, C = loop.noise_state_space(q, r)
    mse_dense = float(np.trace(C @ cl._solve_lyapunov(Ma, B @ B.T) @ C.T)) / (s.n * s.N)
    assert impulse_mse(op, q, r) == pytest.approx(mse_dense, rel=1e-10)
    # ClosedLoop takes the structured path above STRUCTURED_MIN_ORDER
    monkeypatch.setattr(cl, "STRUCTURED_MIN_ORDER", 10)
    again = ClosedLoop(loop.A, loop.W, loop.delays, loop.measure, loop.G)
    assert again.sparse_links
    assert again.spectral_radius() == pytest.approx(rho_dense, rel=1e-10)
    assert again.mse_steady(q, r) == pytest.approx(mse_dense, rel=1e-10)


def test_an_unstable_loop_has_no_impulse_mse():
    s = _communities(4)
    loop = ClosedLoop(s.A * 1.2 / 0.95, s.W, s.delays, s.measure,
                      [np.zeros((s.n, len(m))) for m in s.measure])
    assert loop.spectral_radius() > 1
    with pytest.raises(ValueError, match="not stable|not settled"):
        impulse_mse(LoopOperator(loop), 0.1, 0.1, max_steps=5000)


def test_the_gradient_through_the_operator_is_the_dense_one(monkeypatch):
    """LoopModel's radius gradient from ARPACK on the structured loop (above
    DENSE_SPECTRUM_MAX_ORDER) equals the dense eigenvectors' one."""
    s = _communities(8)
    loop = _delayed_loop(s)
    model = gr.LoopModel(s.A, s.W, loop.delays, s.measure)
    x = model.pack(loop.G)
    monkeypatch.setattr(gr, "DENSE_SPECTRUM_MAX_ORDER", 10 ** 6)
    rho_d, g_d = model.spectral_radius_and_gradient(x)
    monkeypatch.setattr(gr, "DENSE_SPECTRUM_MAX_ORDER", 10)
    model = gr.LoopModel(s.A, s.W, loop.delays, s.measure)
    rho_s, g_s = model.spectral_radius_and_gradient(x)
    assert not model.dense_only
    assert rho_s == pytest.approx(rho_d, rel=1e-10)
    np.testing.assert_allclose(g_s, g_d, rtol=1e-6, atol=1e-8 * np.abs(g_d).max())


def test_a_design_on_communities_16_returns_a_certified_gain():
    """The first stabilising gain the monitor asks for (few iterations); its radius is the
    dense one."""
    from design.reconfigure import fast_recovery_gains

    s = load_scenario("communities-16")
    res = fast_recovery_gains(s, "scenario", max_iter=5)
    assert res.stable
    dense = ClosedLoop(s.A, s.W, s.delays, s.measure, res.G).companion(sparse=False)
    assert res.rho == pytest.approx(float(np.max(np.abs(np.linalg.eigvals(dense)))),
                                    rel=1e-10)


@pytest.mark.parametrize("segment", [1, 3, 32])
def test_the_checkpointed_impulse_gradient_is_the_stored_ones(monkeypatch, segment):
    """A large loop keeps its impulse response only at checkpoints and recomputes it for
    the backward pass: the same operations, so the same MSE and gradient to the bit."""
    s = _communities(4)
    loop = _delayed_loop(s)
    model = gr.LoopModel(s.A, s.W, loop.delays, s.measure)
    x = model.pack(loop.G)
    monkeypatch.setattr(gr, "SPARSE_IMPULSE_MIN_ORDER", 10 ** 6)   # everything stored
    J0, g0, t0 = model.mse_impulse(x, 0.3, 0.7)
    monkeypatch.setattr(gr, "SPARSE_IMPULSE_MIN_ORDER", 1)
    monkeypatch.setattr(gr, "IMPULSE_SEGMENT", segment)
    model = gr.LoopModel(s.A, s.W, loop.delays, s.measure)
    J1, g1, t1 = model.mse_impulse(x, 0.3, 0.7)
    assert t1 == t0 > 3 * segment and loop.taubar >= 2
    assert J1 == pytest.approx(J0, rel=1e-13)
    np.testing.assert_allclose(g1, g0, rtol=1e-10, atol=1e-13 * np.abs(g0).max())


def test_the_impulse_gradient_with_unequal_measured_sets_is_the_dense_one():
    """Agents measuring 1, 2 and 3 nodes (the gain's blocks padded to the widest), with
    heterogeneous delays: the impulse MSE and its gradient against two dense Lyapunov
    solves."""
    s = scenario_from_dict({
        "name": "uneven",
        "social": {"A": (0.9 * np.eye(4) + 0.1 * np.roll(np.eye(4), 1, axis=1)).tolist()},
        "agents": {"measure": [["1"], ["2", "3"], ["1", "3", "4"]]},
        "network": {"weights": [[0.5, 0.5, 0.0], [0.0, 0.5, 0.5], [0.5, 0.0, 0.5]]}})
    D = np.array([[0, 2, 0], [0, 0, 1], [3, 0, 0]])
    model = gr.LoopModel(s.A, s.W, D, s.measure)
    rng = np.random.default_rng(4)
    G = [0.4 * np.eye(s.n)[:, list(m)] + 0.05 * rng.standard_normal((s.n, len(m)))
         for m in s.measure]
    x = model.pack(G)
    assert ClosedLoop(s.A, s.W, D, s.measure, G).spectral_radius() < 0.99
    J, g, _ = model.mse_impulse(x, 0.3, 0.2)
    J_ref, g_ref = model.mse_and_gradient(x, 0.3, 0.2, method="lyapunov")
    assert J == pytest.approx(J_ref, rel=1e-9)
    np.testing.assert_allclose(g, g_ref, rtol=0, atol=1e-9 * np.abs(g_ref).max())


def test_a_loop_whose_links_are_not_strongly_connected_has_its_components_largest_radius():
    """A ring without one agent is a chain: its radius, taken component by component, is
    the dense companion's. (The self-weights differ so that the components' spectra do:
    with equal ones the chain's eigenvalues are defective and the dense solver's are off
    by about eps^(1/4), where the components' are exact.)"""
    s = _communities(6)
    loop = _delayed_loop(s, gain=0.3)
    rows = list(range(1, s.N))
    chain = loop.part(rows)
    chain.W[0, -1] = chain.W[-1, 0] = 0.0          # cut the ring: no path back
    chain.W[np.diag_indices(len(rows))] = [0.35, 0.6, 0.45, 0.5, 0.4]
    chain = ClosedLoop(chain.A, chain.W, chain.delays, chain.measure, chain.G)
    assert len(chain.components()) > 1
    dense = float(np.max(np.abs(np.linalg.eigvals(chain.companion(sparse=False)))))
    assert chain.spectral_radius() == pytest.approx(dense, rel=1e-10)


def test_the_in_place_bfgs_update_is_the_formula():
    rng = np.random.default_rng(5)
    M = rng.standard_normal((7, 7))
    Hinv = M @ M.T + np.eye(7)
    s, y = rng.standard_normal(7), rng.standard_normal(7)
    rho = 1.0 / float(s @ y)
    Hy = Hinv @ y
    expected = (Hinv - rho * (np.outer(s, Hy) + np.outer(Hy, s))
                + (rho * rho * float(y @ Hy) + rho) * np.outer(s, s))
    gr._bfgs_update(Hinv, s, y, rho)
    np.testing.assert_allclose(Hinv, expected, rtol=1e-12, atol=1e-12)


def test_a_bounded_line_search_takes_the_same_iterates():
    """An objective told the line search's threshold may answer inf above it: the
    minimiser's path is the same (such points are rejected either way)."""
    C = np.diag([1.0, 10.0, 100.0])

    def fg(x):
        return float(x @ C @ x) + float(np.sum(x ** 4)), 2 * C @ x + 4 * x ** 3

    def fg_bounded(x, bound):
        f, g = fg(x)
        return (np.inf, np.zeros_like(x)) if f > bound else (f, g)

    x0 = np.array([1.0, -0.7, 0.3])
    plain = gr.bfgs_minimise(fg, x0, max_iter=30)
    bounded = gr.bfgs_minimise(fg_bounded, x0, max_iter=30, bounded=True)
    assert bounded.iterations == plain.iterations > 3
    np.testing.assert_array_equal(bounded.x, plain.x)


def _random_loop(rng):
    """A random delayed loop: 1-5 states, 1-4 agents, delays 0-7, stable or not."""
    n, N = int(rng.integers(1, 6)), int(rng.integers(1, 5))
    A = rng.standard_normal((n, n)) * rng.uniform(0.2, 0.8)
    W = rng.uniform(0, 1, (N, N)) * (rng.uniform(0, 1, (N, N)) < 0.7)
    np.fill_diagonal(W, 1.0)
    W /= W.sum(axis=1, keepdims=True)
    D = np.where(W > 0, rng.integers(0, 8, (N, N)), 0)
    np.fill_diagonal(D, 0)
    measure = [tuple(sorted(rng.choice(n, size=int(rng.integers(1, n + 1)), replace=False)))
               for _ in range(N)]
    G = [0.5 * rng.standard_normal((n, len(m))) for m in measure]
    return ClosedLoop(A, W, D, measure, G)


def test_the_count_of_eigenvalues_outside_a_circle_is_the_dense_eigenvalues_count():
    """The argument principle's count equals the number of dense eigenvalues of modulus
    above the radius whenever it answers, and it answers whenever no eigenvalue is within
    5 % of the circle (150 random loops, 3 circles each, unstable ones included)."""
    rng = np.random.default_rng(7)
    answered = unstable = 0
    for _ in range(150):
        loop = _random_loop(rng)
        moduli = np.abs(np.linalg.eigvals(loop.companion(sparse=False)))
        for c in rng.uniform(0.3, 1.5, 3):
            count = loop.count_outside(c)
            if np.min(np.abs(moduli - c)) > 0.05 * c:
                assert count is not None
            if count is not None:
                assert count == int(np.sum(moduli > c))
                answered += 1
                unstable += count > 0
    assert answered > 350 and unstable > 100


def test_a_counted_bound_is_halfway_to_1_when_every_eigenvalue_is_below_it(monkeypatch):
    """counted_bound (a fast recovery design's warm start): halfway from the target to 1
    when every eigenvalue is counted below it, whether or not some is above the target;
    None when one is above it; no eigenvalue problem is solved for any of them."""
    from design.gain_design import counted_bound

    rng = np.random.default_rng(5)
    while True:                  # a loop with delays of 3-7 steps and a radius near 0.7
        loop = _random_loop(rng)
        loop = ClosedLoop(loop.A, loop.W, np.where(loop.W > 0, 3 + loop.delays % 5, 0)
                          * (1 - np.eye(loop.N, dtype=int)), loop.measure, loop.G)
        if loop.taubar >= 3 and loop.count_pays:
            rho = float(np.max(np.abs(np.linalg.eigvals(loop.companion(sparse=False)))))
            if 0.6 < rho < 0.8:
                break
    monkeypatch.setattr(cl, "spectral_radius",
                        lambda *a, **k: pytest.fail("an eigenvalue problem was solved"))
    assert counted_bound(loop, rho + 0.1) == pytest.approx((1 + rho + 0.1) / 2)
    assert counted_bound(loop, rho - 0.05) == pytest.approx((1 + rho - 0.05) / 2)
    assert counted_bound(loop, 2 * rho - 1.1) is None
    delay_free = ClosedLoop(loop.A, loop.W, np.zeros_like(loop.delays), loop.measure, loop.G)
    assert not delay_free.count_pays and counted_bound(delay_free, 0.99) is None
