"""The Monte-Carlo simulator against hand recursions, the exact steady MSE and itself."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from design import noise
from design.closed_loop import ClosedLoop, closed_loop_for
from design.errors import GainsError
from design.metrics import steady_mse
from design.scenario import scenario_from_dict, uniform_delays
from design.simulate import Recovery, SimulationError, simulate

from design.gain_design import design_gains

# -- a small scenario written out by hand ----------------------------------------------
A3 = [[0.9, 0.3, 0.0], [0.0, 0.8, 0.5], [0.4, 0.0, 1.05]]
W3 = [[0.5, 0.3, 0.2], [0.0, 0.6, 0.4], [0.3, 0.0, 0.7]]
D3 = [[0, 2, 1], [0, 0, 3], [1, 0, 0]]
MEASURE3 = [["1"], ["2", "3"], ["3"]]
G3 = [np.array([[0.5], [0.1], [0.0]]),
      np.array([[0.0, 0.2], [0.4, 0.0], [0.1, 0.6]]),
      np.array([[0.1], [0.0], [0.7]])]


def small_scenario(q=0.0, r=0.0):
    return scenario_from_dict({
        "name": "hand-3",
        "social": {"A": A3, "process_noise": q},
        "agents": {"measure": MEASURE3, "measurement_noise": r},
        "network": {"weights": W3, "delays": D3},
    })


def hand_run(seed, steps, drop=0.0, fail=None, max_age=20):
    """Noise-free estimator written out with explicit matrices (one trial).

    Conventions of docs/simulation.md: xhat_0 from noise.initial_estimate, stamps < 0
    never held, freshest held estimate propagated by A^age while age <= max_age, weight
    of a neighbour with nothing usable held goes to self; failed agents stop computing
    at the failure step, what they published before still arrives and is held.
    """
    A, W, D = np.array(A3), np.array(W3), np.array(D3)
    n, N = 3, 3
    H = [np.eye(n)[[0]], np.eye(n)[[1, 2]], np.eye(n)[[2]]]
    x = noise.initial_state(seed, n)[0]
    xh = [noise.initial_estimate(seed, i + 1, n)[0] for i in range(N)]
    published = {(j, 0): xh[j] for j in range(N)}
    held = {}
    dead = set()
    mse = [np.mean([np.mean((xh[i] - x) ** 2) for i in range(N)])]
    for k in range(1, steps + 1):
        if fail is not None and k == fail[0]:
            dead = set(fail[1])
        x = A @ x
        for i in range(N):
            for j in range(N):
                if i == j or W[i, j] == 0 or i in dead:
                    continue
                s = k - 1 - D[i, j]
                if s < 0 or (j, s) not in published:
                    continue
                if (i, j) in held and held[(i, j)][0] >= s:
                    continue
                if noise.message_dropped(seed, j + 1, i + 1, s, drop)[0]:
                    continue
                held[(i, j)] = (s, published[(j, s)])
        new = {}
        for i in range(N):
            if i in dead:
                continue
            w_self = W[i, i]
            prior = np.zeros(n)
            for j in range(N):
                if j == i or W[i, j] == 0:
                    continue
                if (i, j) in held and k - held[(i, j)][0] <= max_age:
                    s, v = held[(i, j)]
                    prior = prior + W[i, j] * (np.linalg.matrix_power(A, k - s) @ v)
                else:
                    w_self += W[i, j]
            prior = prior + w_self * (A @ xh[i])
            new[i] = prior + G3[i] @ (H[i] @ x - H[i] @ prior)
        for i, v in new.items():
            xh[i] = v
            published[(i, k)] = v
        live = [i for i in range(N) if i not in dead]
        mse.append(np.mean([np.mean((xh[i] - x) ** 2) for i in live]))
    return np.array(mse)


@pytest.mark.parametrize("coordinates", ["error", "absolute"])
@pytest.mark.parametrize("drop, fail, max_age", [(0.0, None, None), (0.5, None, None),
                                                 (0.3, (9, [1]), None), (0.7, None, 5),
                                                 (0.3, (9, [1]), 6)])
def test_zero_noise_matches_hand_recursion(coordinates, drop, fail, max_age):
    s = small_scenario()
    expected = hand_run(seed=5, steps=40, drop=drop, fail=fail,
                        max_age=20 if max_age is None else max_age)
    res = simulate(s, G3, steps=40, trials=1, seed=5, drop=drop, fail=fail,
                   coordinates=coordinates, max_age=max_age)
    np.testing.assert_allclose(res.mse, expected, rtol=1e-11, atol=1e-300)
    assert res.mse_trials.shape == (1, 41)


def test_hand_recursion_is_not_trivial():
    """The drop and failure cases above really differ from the plain run."""
    base = hand_run(5, 40)
    assert not np.allclose(base, hand_run(5, 40, drop=0.5))
    assert not np.allclose(base, hand_run(5, 40, drop=0.3, fail=(9, [1])))


# -- the exact steady MSE ---------------------------------------------------------------


@pytest.fixture(scope="module")
def gain0(paper14):
    result = design_gains(paper14, delays="none", starts=1, max_iter=40, gaps=False)
    assert result.rho < 0.9
    return result.G


def _agrees_with_exact(res, exact):
    assert res.mse_steady == pytest.approx(steady_mse(res.mse), rel=1e-12)
    per_trial = steady_mse(res.mse_trials)
    se = per_trial.std(ddof=1) / np.sqrt(res.trials)
    assert abs(res.mse_steady - exact) < 4 * se, (res.mse_steady, exact, se)
    assert se < 0.1 * exact  # the test has power


def test_steady_mse_delay_free_matches_lyapunov(paper14, gain0):
    D = np.zeros((3, 3), int)
    exact = closed_loop_for(paper14, gain0, D).mse_steady(0.05, 0.05)
    res = simulate(paper14, gain0, steps=400, trials=200, seed=11, delays=D)
    _agrees_with_exact(res, exact)
    assert not res.diverged


def test_steady_mse_with_delays_matches_exact(paper14, gain0):
    G, D = gain0, uniform_delays(paper14.W, 1)
    loop = closed_loop_for(paper14, G, D)
    exact = loop.mse_steady(0.05, 0.05)
    # the delay-free prediction is a different number: the check can tell them apart
    assert loop.spectral_radius() < 1
    assert abs(exact - ClosedLoop(paper14.A, paper14.W, 0 * D, paper14.measure, G)
               .mse_steady(0.05, 0.05)) > 0.3 * exact
    res = simulate(paper14, G, steps=400, trials=200, seed=12, delays=D)
    _agrees_with_exact(res, exact)


@pytest.mark.slow
def test_error_coordinates_stay_accurate_for_unstable_A(paper14, gain0):
    """3000 steps with rho(A) = 1.086: x grows ~1e107, the error keeps full precision."""
    D = np.zeros((3, 3), int)
    exact = closed_loop_for(paper14, gain0, D).mse_steady(0.05, 0.05)
    res = simulate(paper14, gain0, steps=3000, trials=40, seed=3, delays=D)
    _agrees_with_exact(res, exact)
    absolute = simulate(paper14, gain0, steps=3000, trials=2, seed=3, delays=D,
                        coordinates="absolute")
    # absolute coordinates have lost every digit of the error by then
    assert not np.allclose(absolute.mse_trials[:, -1], res.mse_trials[:2, -1], rtol=0.5)
    # ... but agree at the start, before the digits are gone
    np.testing.assert_allclose(absolute.mse_trials[:, :40], res.mse_trials[:2, :40], rtol=1e-9)


def test_error_and_absolute_coordinates_agree_when_A_is_stable(gain0):
    from design.scenario import load_scenario

    s = load_scenario("paper-14-live")
    G = design_gains(s, delays="none", starts=1, max_iter=40).G
    kw = dict(steps=150, trials=5, seed=4, delays=uniform_delays(s.W, 2), drop=0.2)
    a = simulate(s, G, coordinates="error", **kw)
    b = simulate(s, G, coordinates="absolute", **kw)
    np.testing.assert_allclose(a.mse_trials, b.mse_trials, rtol=1e-10)


# -- stability, reproducibility ---------------------------------------------------------


def test_unstable_loop_diverges_and_stable_one_does_not(paper14, gain0):
    D = uniform_delays(paper14.W, 1)
    for G, stable in [(gain0, True), ([np.zeros((14, 1))] * 3, False)]:
        rho = closed_loop_for(paper14, G, D).spectral_radius()
        assert (rho < 1) == stable
        res = simulate(paper14, G, steps=300, trials=10, seed=1, delays=D)
        assert res.diverged == (not stable), (rho, res.mse_steady)


def test_same_seed_same_numbers_and_trial0_is_single_run(paper14, gain0):
    kw = dict(steps=60, delays=uniform_delays(paper14.W, 2), drop=0.3, fail=(30, [2]))
    a = simulate(paper14, gain0, trials=6, seed=8, **kw)
    b = simulate(paper14, gain0, trials=6, seed=8, **kw)
    assert np.array_equal(a.mse_trials, b.mse_trials)
    c = simulate(paper14, gain0, trials=6, seed=9, **kw)
    assert not np.allclose(a.mse_trials, c.mse_trials)
    one = simulate(paper14, gain0, trials=1, seed=8, **kw)
    np.testing.assert_allclose(one.mse_trials[0], a.mse_trials[0], rtol=1e-12)


def test_drop_zero_is_no_drop_and_drops_change_the_run(paper14, gain0):
    kw = dict(steps=50, trials=4, seed=2, delays=uniform_delays(paper14.W, 1))
    base = simulate(paper14, gain0, **kw)
    assert np.array_equal(base.mse_trials, simulate(paper14, gain0, drop=0.0, **kw).mse_trials)
    assert np.array_equal(base.mse_trials, simulate(paper14, gain0, drop=1e-15, **kw).mse_trials)
    assert not np.allclose(base.mse_trials, simulate(paper14, gain0, drop=0.5, **kw).mse_trials)


def test_message_dropped_stream():
    a = noise.message_dropped(1, 2, 3, 4, 0.5, trials=1000)
    assert a.shape == (1000,) and 400 < a.sum() < 600
    assert a[0] == noise.message_dropped(1, 2, 3, 4, 0.5)[0]
    assert np.all(noise.message_dropped(1, 2, 3, 4, 0.3, 1000) <= a)   # monotone in p
    assert not np.array_equal(a, noise.message_dropped(1, 3, 2, 4, 0.5, 1000))


# -- failure and recovery ---------------------------------------------------------------


def test_recovery_handover_is_seamless_without_noise_or_delay(paper14, gain0):
    """A replacement with the same sensor and gain, taking over the failed agent's
    estimate, continues exactly as the agent would have (no noise, no delay)."""
    s = paper14.replace(process_noise=0.0, measurement_noise=0.0,
                        delays=np.zeros((3, 3), int))
    plan = Recovery(scenario=s, G=gain0, ids=(1, 4, 3), replaces={4: 1})
    base = simulate(s, gain0, steps=40, trials=3, seed=6)
    rec = simulate(s, gain0, steps=40, trials=3, seed=6, fail=(20, [1]), recover=plan)
    np.testing.assert_allclose(rec.mse_trials, base.mse_trials, rtol=1e-12)
    cold = Recovery(scenario=s, G=gain0, ids=(1, 4, 3))
    res = simulate(s, gain0, steps=40, trials=3, seed=6, fail=(20, [1]), recover=cold)
    assert np.all(res.mse_trials[:, 20] > 10 * base.mse_trials[:, 20])   # cold start


def test_failure_removes_the_agent_from_the_mse(paper14, gain0):
    s = paper14.replace(process_noise=0.0, measurement_noise=0.0)
    res = simulate(s, gain0, steps=10, trials=2, seed=6, fail=(5, [0, 1]))
    base = simulate(s, gain0, steps=10, trials=2, seed=6)
    assert np.array_equal(res.mse_trials[:, :5], base.mse_trials[:, :5])
    assert not np.allclose(res.mse_trials[:, 5], base.mse_trials[:, 5])


def test_recovery_plan_reaches_the_new_loops_steady_mse(paper14, gain0):
    from design.recovery import plan_recovery

    big = paper14.replace(standby=2)
    plan = plan_recovery(big, [0, 1])
    new = plan.scenario_after
    assert [new.agent_labels(i) for i in range(new.N)] == [["8"], ["10"], ["12"]]
    G2 = design_gains(new, starts=1, max_iter=40).G
    rec = Recovery.from_plan(plan, G2)
    assert rec.ids == (4, 5, 3) and rec.replaces == {4: 0, 5: 1}
    res = simulate(big, gain0, steps=500, trials=100, seed=7, fail=(100, [0, 1]), recover=rec)
    exact = closed_loop_for(new, G2).mse_steady(0.05, 0.05)
    _agrees_with_exact(res, exact)


# -- bad input --------------------------------------------------------------------------


@pytest.mark.parametrize("kwargs, match", [
    (dict(steps=0), "steps"),
    (dict(trials=-1), "trials"),
    (dict(seed=1.5), "seed"),
    (dict(drop=1.0), "drop"),
    (dict(drop=-0.1), "drop"),
    (dict(fail=(0, [1])), "fail step"),
    (dict(fail=(99, [1])), "after the last step"),
    (dict(fail=(5, [3])), "no agent row 3"),
    (dict(fail=(5, [0, 1, 2])), "every agent fails"),
    (dict(fail="x"), "fail"),
    (dict(coordinates="polar"), "coordinates"),
    (dict(delays=np.ones((3, 3), int)), "delays"),
])
def test_bad_arguments_are_named(paper14, gain0, kwargs, match):
    kw = dict(steps=20, trials=2, seed=0)
    kw.update(kwargs)
    with pytest.raises(SimulationError, match=match):
        simulate(paper14, gain0, **kw)


def test_gains_that_do_not_fit(paper14):
    with pytest.raises(GainsError, match="K2"):
        simulate(paper14, [np.zeros((14, 1)), np.zeros((14, 2)), np.zeros((14, 1))], 5, 1, 0)


def test_recovery_must_keep_A(paper14, gain0):
    other = paper14.replace(A=paper14.A * 0.5)
    plan = Recovery(scenario=other, G=gain0, ids=(1, 4, 3), replaces={4: 1})
    with pytest.raises(SimulationError, match="social matrix"):
        simulate(paper14, gain0, 10, 1, 0, fail=(5, [1]), recover=plan)
    with pytest.raises(SimulationError, match="needs a failure"):
        simulate(paper14, gain0, 10, 1, 0, recover=plan)


def test_recorded_estimates_are_the_absolute_run(paper14):
    """record_estimates keeps xhat of every agent; its error reproduces the MSE."""
    import numpy as np

    from design import noise
    from design.simulate import simulate

    rng = np.random.default_rng(3)
    G = [0.2 * rng.normal(size=(paper14.n, 1)) for _ in range(paper14.N)]
    res = simulate(paper14, G, steps=12, trials=2, seed=5, coordinates="absolute",
                   record_estimates=True)
    assert res.estimates.shape == (2, 13, paper14.N, paper14.n)
    x = noise.initial_state(5, paper14.n, 2)
    for k in range(1, 13):
        x = x @ paper14.A.T + noise.process_noise(5, k - 1, paper14.n, paper14.process_noise, 2)
    e = res.estimates[:, 12] - x[:, None, :]
    np.testing.assert_allclose(np.mean(e * e, axis=(1, 2)), res.mse_trials[:, 12], rtol=1e-10)
    np.testing.assert_array_equal(res.estimates[:, 0, 0],
                                  noise.initial_estimate(5, 1, paper14.n, 2))


def test_record_estimates_needs_absolute_coordinates(paper14):
    import numpy as np
    import pytest

    from design.simulate import SimulationError, simulate

    G = [np.zeros((paper14.n, 1))] * paper14.N
    with pytest.raises(SimulationError, match="record_estimates"):
        simulate(paper14, G, steps=2, trials=1, seed=0, record_estimates=True)


@given(st.lists(st.tuples(st.integers(0, 60), st.integers(1, 5)), min_size=1, max_size=30),
       st.integers(1, 8))
@settings(max_examples=60, deadline=None)
def test_draws_computed_ahead_equal_the_one_off_draws(queries, block):
    """Whatever steps and sizes a process asks in whatever order (a role that measures
    more nodes, a catch-up, a restart), the draws held ahead are the one-off draws."""
    meas = noise.StepDraws(lambda k, p: noise.measurement_noise(5, 3, k, p, 0.2)[0], block)
    proc = noise.StepDraws(lambda k, n: noise.process_noise(5, k, n, 0.05)[0], block)
    for step, size in queries:
        assert np.array_equal(meas(step, size), noise.measurement_noise(5, 3, step, size, 0.2)[0])
        assert np.array_equal(proc(step, size), noise.process_noise(5, step, size, 0.05)[0])
