"""The plausibility bound (design.plausibility) never refuses what a healthy run computes:
every estimate and every true state of simulated runs, stable and unstable, with delays
and a failure, stays within it, far inside."""

import numpy as np
import pytest

from design.plausibility import ESTIMATE_MULTIPLE, READING_MULTIPLE, StateScale
from design.scenario import load_scenario, resolve_delays
from design.simulate import simulate


@pytest.mark.parametrize("name, fail", [("paper-14", None), ("paper-14-live", (120, [0])),
                                        ("paper-14-live", None)])
def test_simulated_runs_stay_far_inside_the_bound(name, fail):
    s = load_scenario(name)
    G = [0.5 * np.eye(s.n)[:, list(m)] for m in s.measure]
    steps = 300
    r = simulate(s, G, steps=steps, trials=3, seed=11, delays=resolve_delays(s, "scenario"),
                 coordinates="absolute", record_estimates=True, fail=fail)
    scale = StateScale(s.A, s.process_noise, s.measurement_noise)
    est = np.asarray(r.estimates)                         # (trials, steps + 1, agents, n)
    worst = max(np.nanmax(np.abs(est[:, k])) / scale.sigma(k) for k in range(steps + 1))
    assert worst < ESTIMATE_MULTIPLE / 100, worst
    for k in range(steps + 1):
        assert scale.plausible(est[:, k][np.isfinite(est[:, k])], k, ESTIMATE_MULTIPLE)


def test_the_state_of_an_unstable_system_stays_inside_the_reading_bound():
    """x_{k+1} = A x_k + nu_k from x_0 ~ N(0, I), 600 steps of paper-14 (rho 1.086):
    the largest entry over 20 draws is a few sigma_k at every step."""
    s = load_scenario("paper-14")
    scale = StateScale(s.A, s.process_noise, s.measurement_noise)
    rng = np.random.default_rng(5)
    x = rng.standard_normal((20, s.n))
    worst = 0.0
    for k in range(600):
        worst = max(worst, float(np.max(np.abs(x))) / scale.sigma(k))
        x = x @ s.A.T + np.sqrt(s.process_noise) * rng.standard_normal(x.shape)
    assert worst < READING_MULTIPLE / 100, worst


def test_the_bound_tracks_growth_and_keeps_the_initial_scale():
    """Unstable: sigma_k grows at least like rho^k. Stable: never below the initial
    scale, and flat once the transient settled."""
    grow = StateScale(np.array([[1.1, 0.0], [0.0, 0.5]]), q=0.0)
    assert all(grow.sigma(k) >= (1 - 1e-12) * 1.1 ** k for k in (10, 63, 64, 200, 1000))
    settle = StateScale(0.5 * np.eye(3), q=0.01, r=0.02)
    assert settle.growth == 1.0
    assert settle.sigma(5000) == settle.sigma(64) >= 1.0
