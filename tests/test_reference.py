"""Exact grid posteriors and the 1-D Wasserstein distance against closed forms."""

import math

import jax
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


def test_grid_filter_matches_the_scalar_kalman_filter(x64):
    # X_0 ~ N(0, 1), X_t = 0.8 X_{t-1} + 0.5 V, y_t = X_t + 0.3 W: the Kalman recursion is exact.
    from ot_filter.reference import grid_filter

    rng = np.random.default_rng(0)
    ys = rng.normal(size=30) * 1.5
    result = grid_filter(
        lambda y, x: -0.5 * ((y - x) / 0.3) ** 2, jnp.asarray(ys), jnp.linspace(-8.0, 8.0, 1601),
        lambda x: -0.5 * x**2, lambda x: 0.8 * x, 0.5,
    )
    mean, var = 0.0, 1.0
    for t, y in enumerate(ys):
        mean, var = 0.8 * mean, 0.64 * var + 0.25
        gain = var / (var + 0.09)
        mean, var = mean + gain * (y - mean), (1 - gain) * var
        grid_mean = float(result.masses[t] @ result.grid)
        grid_var = float(result.masses[t] @ result.grid**2) - grid_mean**2
        # Riemann sums of Gaussians on a fine grid: error far below 1e-6 (dx = 0.01, sd >= 0.26).
        assert abs(grid_mean - mean) < 1e-6 and abs(grid_var - var) < 1e-6
    assert float(jnp.max(jnp.abs(result.lost_mass))) < 1e-10


def test_squared_observation_filter_keeps_the_modes_exactly_symmetric():
    from ot_filter.experiments.dynamic_example import exact_positive_mass

    model = otf.models.squared_observation(dim=3)
    _, ys = otf.simulate(jax.random.PRNGKey(3), model, 40)
    result = otf.reference.squared_observation_filter(ys)
    assert result.masses.shape == (3, 40, 901)
    np.testing.assert_allclose(np.asarray(result.masses.sum(-1)), 1.0, atol=1e-5)
    positive = exact_positive_mass(jax.tree.map(lambda a: a[None], result))
    np.testing.assert_allclose(positive, 0.5, atol=1e-5)
    assert float(jnp.max(jnp.abs(result.lost_mass))) < 1e-3
    # The posterior mean of x^2 follows the observations (modes near +-sqrt(y) when y is large).
    second_moment = np.asarray(result.masses @ result.grid**2).T  # [T, n]
    large = np.asarray(ys) > 2.0
    assert large.any()
    np.testing.assert_allclose(second_moment[large], np.asarray(ys)[large], rtol=0.2)


def test_mmd_to_product_is_the_exact_mmd_to_the_discrete_product_measure():
    from ot_filter.metrics import mmd, mmd_to_product

    rng = np.random.default_rng(1)
    grid = np.linspace(-2.0, 2.0, 21)
    masses = rng.random((2, 21)) ** 3
    masses /= masses.sum(axis=1, keepdims=True)
    # The product measure as 21 x 21 weighted atoms.
    atoms = np.stack(np.meshgrid(grid, grid, indexing="ij"), -1).reshape(-1, 2)
    atom_weights = np.outer(masses[0], masses[1]).ravel()
    x = grid[rng.integers(0, 21, size=(50, 2))]  # on grid nodes: interpolation is exact there
    w = rng.random(50)
    for bandwidth in (0.7, np.array([0.5, 1.5])):
        scale = np.broadcast_to(bandwidth, (2,))
        expected = mmd(x / scale, atoms / scale, 1.0, x_weights=w, y_weights=atom_weights)
        got = mmd_to_product(jnp.asarray(x), jnp.asarray(grid), jnp.asarray(masses), bandwidth, weights=w)
        assert abs(float(got) - float(expected)) < 1e-5
    # Off the nodes the linear interpolation of the smoothed reference costs O(dx^2 / h^2).
    x_off = rng.uniform(-2, 2, size=(50, 2))
    expected = mmd(x_off, atoms, 1.0, y_weights=atom_weights)
    got = mmd_to_product(jnp.asarray(x_off), jnp.asarray(grid), jnp.asarray(masses), 1.0)
    assert abs(float(got) - float(expected)) < 0.01


def test_mmd_to_product_rejects_mismatched_masses():
    from ot_filter.metrics import mmd_to_product

    with pytest.raises(ValueError, match="masses"):
        mmd_to_product(jnp.zeros((5, 2)), jnp.linspace(-1, 1, 11), jnp.ones((3, 11)))
    with pytest.raises(ValueError, match="bandwidth"):
        mmd_to_product(jnp.zeros((5, 2)), jnp.linspace(-1, 1, 11), jnp.ones((2, 11)), bandwidth=0.0)


def test_exact_comparison_and_floor_match_the_metrics_pair_by_pair():
    """The dynamic example's batched comparison (padded to whole batches: 2 x 5 = 10 pairs, not a
    multiple of 8) and its floor (computed once per run) against ``compare_to_product_grid`` called
    on each (simulation, time) pair with the keys the docstrings promise."""
    from ot_filter.experiments.dynamic_example import exact_comparison, exact_floor, exact_posteriors
    from ot_filter.metrics import compare_to_product_grid, product_grid_sample

    # Float64: the energy distance is a difference of O(1) terms (float32 leaves 1e-6 of it to
    # the order of the sums, which batching changes).
    with jax.enable_x64(True):
        model = otf.models.squared_observation(dim=2)
        ys = jnp.stack([otf.simulate(jax.random.PRNGKey(s), model, 5)[1] for s in range(2)])  # [S, T, n]
        reference = exact_posteriors(ys)
        num = 40
        particles = jax.random.normal(jax.random.PRNGKey(7), (2, 5, num, 2))
        log_weights = jax.nn.log_softmax(jax.random.normal(jax.random.PRNGKey(8), (2, 5, num)), axis=-1)
        key = jax.random.PRNGKey(9)
        found = exact_comparison(key, particles, log_weights, reference)
        floor = exact_floor(key, num, reference)
        pair_keys = jax.random.split(key, 10)
        for s in range(2):
            for t in range(5):
                floor_key, compare_key = jax.random.split(pair_keys[5 * s + t])
                masses = reference.masses[s, :, t]
                expected = compare_to_product_grid(compare_key, particles[s, t], jnp.exp(log_weights[s, t]),
                                                   reference.grid[s], masses, num)
                exact = product_grid_sample(floor_key, reference.grid[s], masses, num)
                expected_floor = compare_to_product_grid(compare_key, exact, None, reference.grid[s], masses, num)
                # The energy distance's self-pairs are sqrt of a rounded |a|^2 + |b|^2 - 2ab ~ 1e-16:
                # up to sqrt(8 eps) |x| ~ 4e-8 * 3 each, however the sums are ordered. A wrong key
                # or pair moves any of these by ~1e-2.
                for name, atol in (("w1", 1e-12), ("sliced_w2", 1e-12), ("energy", 2e-7)):
                    np.testing.assert_allclose(found[name][s, t], getattr(expected, name), rtol=1e-9, atol=atol)
                    np.testing.assert_allclose(floor["floor_" + name][s, t], getattr(expected_floor, name),
                                               rtol=1e-9, atol=atol)
