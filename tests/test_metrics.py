"""Metrics against closed forms (Gaussian MMD, energy distance, CRPS) and basic identities."""

import math

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ot_filter import metrics


def gaussian_mmd_squared(shift, sigma, bandwidth, dim):
    """MMD^2 between N(0, s^2 I) and N(shift, s^2 I) with the Gaussian kernel of bandwidth h."""
    total = bandwidth**2 + 2 * sigma**2
    c = (bandwidth**2 / total) ** (dim / 2)
    return 2 * c * (1 - math.exp(-np.sum(np.square(shift)) / (2 * total)))


def test_mmd_matches_closed_form():
    num, dim, h = 4000, 2, 1.0
    shift = np.array([0.6, -0.2])
    x = jax.random.normal(jax.random.key(0), (num, dim))
    y = jax.random.normal(jax.random.key(1), (num, dim)) + shift
    exact = gaussian_mmd_squared(shift, 1.0, h, dim)
    unbiased = float(metrics.mmd(x, y, bandwidth=h, unbiased=True, squared=True))
    # U-statistic standard deviation at this size is about 3e-3 (checked by replication).
    assert abs(unbiased - exact) < 0.015
    # The V-statistic adds the diagonal terms: E = exact + (1 - E k(X, X')) (1/N + 1/M).
    biased = float(metrics.mmd(x, y, bandwidth=h, squared=True))
    same_kernel_mean = (h**2 / (h**2 + 2.0)) ** (dim / 2)
    expected_biased = exact + (1 - same_kernel_mean) * 2 / num
    assert abs(biased - unbiased - (expected_biased - exact)) < 1e-4
    same = float(metrics.mmd(x, jax.random.normal(jax.random.key(2), (num, dim)), bandwidth=h))
    assert same < 0.05 < math.sqrt(exact)


def test_mmd_blocking_and_weights_are_exact_rewrites():
    x = jax.random.normal(jax.random.key(0), (301, 3))
    y = jax.random.normal(jax.random.key(1), (157, 3)) + 0.3
    reference = metrics.mmd(x, y, bandwidth=0.8, block_size=4096)
    np.testing.assert_allclose(metrics.mmd(x, y, bandwidth=0.8, block_size=7), reference, rtol=1e-4)
    # Integer weights = repeated samples.
    counts = np.random.default_rng(0).integers(1, 4, size=157)
    repeated = jnp.repeat(y, counts, axis=0)
    np.testing.assert_allclose(
        metrics.mmd(x, y, bandwidth=0.8, y_weights=counts), metrics.mmd(x, repeated, bandwidth=0.8),
        rtol=1e-4,
    )
    assert float(metrics.median_bandwidth(x, y)) > 0
    assert np.isfinite(metrics.mmd(x, y))  # median heuristic


def test_mmd_rejects_bad_input():
    x = jnp.zeros((5, 2))
    with pytest.raises(ValueError, match="dimension"):
        metrics.mmd(x, jnp.zeros((5, 3)))
    with pytest.raises(ValueError, match="bandwidth"):
        metrics.mmd(x, x, bandwidth=0.0)
    with pytest.raises(ValueError, match="unbiased"):
        metrics.mmd(x, x, unbiased=True, x_weights=jnp.ones(5))
    with pytest.raises(ValueError, match="y_weights"):
        metrics.mmd(x, x, y_weights=jnp.ones(4))
    with pytest.raises(ValueError, match="x_weights"):
        metrics.mmd(x, x, x_weights=-jnp.ones(5))
    with pytest.raises(ValueError, match="block_size"):
        metrics.energy_distance(x, x, block_size=0)
    # A traced bandwidth is accepted (no float() of a tracer).
    assert np.isfinite(jax.jit(lambda h: metrics.mmd(x, x + 1.0, bandwidth=h))(1.0))


@pytest.mark.long
def test_mmd_large_samples_in_bounded_memory():
    """10^5 x 10^4 samples: blocks of 1024^2 kernel values, never a 10^5 x 10^5 matrix."""
    x = jax.random.normal(jax.random.key(0), (100_000, 2))
    y = jax.random.normal(jax.random.key(1), (10_000, 2))
    value = float(metrics.mmd(x, y, bandwidth=1.0))
    assert 0 <= value < 0.03


def test_energy_distance_matches_closed_form_in_1d():
    num, shift = 20_000, 0.8
    x = jax.random.normal(jax.random.key(0), (num,))
    y = jax.random.normal(jax.random.key(1), (num,)) + shift
    sigma = math.sqrt(2.0)  # X - Y ~ N(-shift, 2)
    expected_xy = sigma * math.sqrt(2 / math.pi) * math.exp(-shift**2 / (2 * sigma**2)) + shift * math.erf(
        shift / (sigma * math.sqrt(2))
    )
    expected = 2 * expected_xy - 2 * (2 / math.sqrt(math.pi))
    assert abs(float(metrics.energy_distance(x, y)) - expected) < 0.02


def test_crps_matches_gaussian_closed_form():
    truth = jnp.array([0.3, -1.2])
    ensemble = jax.random.normal(jax.random.key(0), (100_000, 2))
    z = np.asarray(truth, np.float64)
    phi = np.exp(-z**2 / 2) / np.sqrt(2 * np.pi)
    cdf = 0.5 * (1 + np.vectorize(math.erf)(z / np.sqrt(2)))
    exact = z * (2 * cdf - 1) + 2 * phi - 1 / np.sqrt(np.pi)
    np.testing.assert_allclose(metrics.crps(ensemble, truth), exact, atol=5e-3)
    small = ensemble[:5]
    assert np.all(metrics.crps(small, truth, fair=True) < metrics.crps(small, truth))


class TestSimpleMetrics(chex.TestCase):
    """Closed forms of the plain (not internally jitted) metrics, called eagerly and inside
    jax.jit: chex runs the test once per variant (test_simple_metrics__with_jit, __without_jit)."""

    @chex.variants(with_jit=True, without_jit=True)
    def test_simple_metrics(self):
        mse, rmse, ess, spread = map(self.variant, (metrics.mse, metrics.rmse, metrics.ess, metrics.spread))
        estimate, truth = jnp.array([[1.0, 2.0], [0.0, 0.0]]), jnp.array([[1.0, 0.0], [3.0, 4.0]])
        np.testing.assert_allclose(mse(estimate, truth), [2.0, 12.5])
        np.testing.assert_allclose(rmse(estimate, truth), np.sqrt([2.0, 12.5]))
        np.testing.assert_allclose(ess(jnp.zeros(10)), 10.0, rtol=1e-6)
        np.testing.assert_allclose(ess(jnp.full(10, -jnp.inf).at[2].set(0.0)), 1.0)
        particles = jax.random.normal(jax.random.key(0), (50, 3))
        expected = np.sqrt(np.mean(np.var(np.asarray(particles), axis=0, ddof=1)))
        np.testing.assert_allclose(spread(particles), expected, rtol=1e-5)
        np.testing.assert_allclose(spread(particles, jnp.zeros(50)), expected, rtol=1e-5)
        # Weighted: the unbiased weighted variance, computed independently in float64.
        log_weights = jnp.linspace(-3.0, 1.0, 50)
        w = np.exp(np.asarray(log_weights, np.float64))
        w /= w.sum()
        x = np.asarray(particles, np.float64)
        variance = w @ (x - w @ x) ** 2 / (1 - np.sum(w**2))
        np.testing.assert_allclose(spread(particles, log_weights), np.sqrt(variance.mean()), rtol=1e-5)


@pytest.mark.long
def test_median_bandwidth_ignores_duplicates():
    resampled = jnp.repeat(jnp.array([[0.0], [1.0], [3.0]]), jnp.array([40, 2, 2]), axis=0)
    bandwidth = float(metrics.median_bandwidth(resampled, resampled))
    assert bandwidth > 0.5
    assert np.isfinite(metrics.mmd(resampled, resampled + 0.1))
    assert float(metrics.median_bandwidth(jnp.zeros((5, 2)), jnp.zeros((5, 2)))) == 1.0
