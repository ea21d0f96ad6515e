import numpy as np
import pytest

from design.metrics import steady_mse, steady_window


@pytest.mark.parametrize("steps, window", [(1, 1), (4, 1), (7, 1), (8, 2), (11, 2), (12, 3)])
def test_window_is_a_quarter_rounded_down_but_at_least_one(steps, window):
    assert steady_window(steps) == window


def test_steady_mse_by_hand():
    assert steady_mse([100.0, 50, 20, 10, 8, 6, 4, 2]) == 3.0     # (4 + 2) / 2
    assert steady_mse([7.0]) == 7.0
    per_trial = steady_mse(np.array([[0.0] * 9 + [1, 2, 3], [5.0] * 9 + [0, 0, 3]]))
    np.testing.assert_allclose(per_trial, [2.0, 1.0])


def test_empty_series_is_an_error():
    with pytest.raises(ValueError, match="mse"):
        steady_mse([])
