"""Exact grid posteriors and the 1-D Wasserstein distance against closed forms."""

import math

import jax.numpy as jnp
import numpy as np
import pytest

import ot_filter as otf
from ot_filter.reference import grid_posterior, squared_observation_posterior


def test_grid_posterior_of_a_conjugate_gaussian_is_exact(x64):
    # X ~ N(1, 4), y = X + N(0, 0.5^2), y = 2: posterior N(m, v) in closed form.
    prior_mean, prior_var, noise_var, y = 1.0, 4.0, 0.25, 2.0
    v = 1.0 / (1.0 / prior_var + 1.0 / noise_var)
    m = v * (prior_mean / prior_var + y / noise_var)
    exact = grid_posterior(
        lambda x: -0.5 * (x - prior_mean) ** 2 / prior_var - 0.5 * (y - x) ** 2 / noise_var, -10.0, 12.0
    )
    dx = float(exact.grid[1] - exact.grid[0])
    mean = float(jnp.sum(exact.grid * exact.density) * dx)
    var = float(jnp.sum((exact.grid - mean) ** 2 * exact.density) * dx)
    assert abs(mean - m) < 1e-8 and abs(var - v) < 1e-8
    assert float(exact.cdf[-1]) == pytest.approx(1.0) and float(exact.edge_mass) < 1e-12


def test_squared_observation_posterior_is_symmetric_with_modes_at_sqrt_2y():
    exact = squared_observation_posterior(1.0, 0.04)
    middle = exact.grid.shape[0] // 2
    assert float(exact.cdf[middle]) == pytest.approx(0.5, abs=1e-4)
    assert abs(abs(float(exact.grid[jnp.argmax(exact.density)])) - math.sqrt(2.0)) < 0.01


def test_wasserstein_1d_closed_forms(x64):
    standard = grid_posterior(lambda x: -0.5 * x**2, -10.0, 10.0, 40_001)
    for c in (0.0, 0.7, 3.0):
        # W1(delta_c, N(0, 1)) = E|Z - c| = 2 phi(c) + c (2 Phi(c) - 1).
        phi = math.exp(-0.5 * c * c) / math.sqrt(2 * math.pi)
        Phi = 0.5 * (1 + math.erf(c / math.sqrt(2)))
        expected = 2 * phi + c * (2 * Phi - 1)
        got = float(otf.metrics.wasserstein_1d(jnp.array([c]), standard.grid, standard.cdf))
        assert got == pytest.approx(expected, abs=1e-3)
    # Weights: mass 0.25 at -1 and 0.75 at 2 against the point mass at 2 (a grid CDF step):
    # W1 = 0.25 * 3.
    grid = jnp.linspace(-5.0, 5.0, 100_001)
    cdf = (grid >= 2.0).astype(grid.dtype)
    got = otf.metrics.wasserstein_1d(jnp.array([-1.0, 2.0]), grid, cdf, weights=jnp.array([1.0, 3.0]))
    assert float(got) == pytest.approx(0.75, abs=1e-3)
    # Samples outside the grid are transported to its end.
    assert float(otf.metrics.wasserstein_1d(jnp.array([7.0]), grid, cdf)) == pytest.approx(5.0, abs=1e-3)


def test_reference_and_metric_input_errors():
    with pytest.raises(ValueError, match="upper"):
        grid_posterior(lambda x: -x * x, 1.0, 0.0)
    grid = jnp.linspace(0, 1, 11)
    with pytest.raises(ValueError, match="samples"):
        otf.metrics.wasserstein_1d(jnp.ones((3, 2)), grid, grid)
    with pytest.raises(ValueError, match="grid and cdf"):
        otf.metrics.wasserstein_1d(jnp.ones(3), grid, grid[:5])
    with pytest.raises(ValueError, match="weights"):
        otf.metrics.wasserstein_1d(jnp.ones(3), grid, grid, weights=-jnp.ones(3))
