"""The step test of experiments/bias_detectability.py: exact on noiseless steps, χ²(2) on noise."""

import numpy as np

from experiments.bias_detectability import paired, single, steps


def _line(n: int = 60) -> tuple[np.ndarray, np.ndarray]:
    t = np.cumsum(np.r_[0.0, np.random.default_rng(1).uniform(0.5, 1.5, n - 1)])
    return t, np.stack([3.0 + 2.0 * t, -1.0 + 0.5 * t], 1)


def test_a_step_on_a_straight_line_is_found_exactly_where_it_is() -> None:
    t, z = _line()
    z[30:] += [4.0, -3.0]
    for degree in (1, 2):
        step, _ = steps(t, z, 1.0, 8, degree)
        # boundary k sits at index k - 1; windows that hold the step on one side only
        np.testing.assert_allclose(step[29], [4.0, -3.0], atol=1e-9)
        far = np.r_[3:21, 38:55]  # where both sides have the rows a fit needs
        np.testing.assert_allclose(step[far], 0.0, atol=1e-8)
        assert np.isnan(step[0]).all()  # one row on the left: no fit


def test_the_statistic_is_chi_square_with_two_degrees_on_noise() -> None:
    rng = np.random.default_rng(0)
    t, z = _line(400)
    stats = []
    for _ in range(20):
        noisy = z + rng.normal(0.0, 2.0, z.shape)
        step, var = steps(t, noisy, 2.0, 10, 2)
        stats.append(single(step, var)[20:-20])
    mean = np.concatenate(stats).mean()
    assert abs(mean - 2.0) < 0.15, mean


def test_the_paired_test_joins_an_on_and_an_off_step() -> None:
    t, z = _line()
    z[20:40] += [3.0, 0.0]
    step, var = steps(t, z, 1.0, 6, 1)
    pair = paired(step, var, 6)
    # the bias on at boundary 20 and off at 40: both steps say 3, so the pair says 3 with
    # half the variance of one
    i, j = 19, 39
    assert pair[i, j] > single(step, var)[i] * 1.9
    assert pair[j, i] == 0.0  # only on before off
