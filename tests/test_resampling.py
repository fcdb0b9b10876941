"""Resampling schemes: unbiased offspring counts, structural guarantees, degenerate weights."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ot_filter as otf
from ot_filter.updates.resampling import RESAMPLING_SCHEMES

NUM = 50
REPLICATIONS = 4000


def offspring_counts(scheme, log_weights, key):
    keys = jax.random.split(key, REPLICATIONS)
    indices = jax.vmap(lambda k: otf.resample_indices(k, log_weights, scheme))(keys)
    return np.asarray(jax.vmap(lambda i: jnp.bincount(i, length=NUM))(indices))


@pytest.fixture(scope="module")
def log_weights():
    rng = np.random.default_rng(0)
    raw = rng.exponential(size=NUM) ** 3  # spread-out weights, some tiny, some several / N
    raw[3] = 8.0 * raw.sum() / NUM  # one dominant particle: N w > 1
    return jnp.log(jnp.asarray(raw / raw.sum(), jnp.float32)) + 123.0  # any normalisation


@pytest.mark.parametrize("scheme", sorted(RESAMPLING_SCHEMES))
def test_offspring_counts_are_unbiased(scheme, log_weights):
    counts = offspring_counts(scheme, log_weights, jax.random.key(1))
    assert np.all(counts.sum(axis=1) == NUM)
    expected = NUM * np.exp(np.asarray(log_weights, np.float64) - jax.nn.logsumexp(log_weights))
    # An integer count with mean mu has variance >= frac(mu) (1 - frac(mu)): a floor for the
    # empirical variance of rarely drawn particles (never drawn in 4000 tries, say).
    fraction = expected - np.floor(expected)
    variance = np.maximum(counts.var(axis=0, ddof=1), fraction * (1 - fraction))
    z = np.abs(counts.mean(axis=0) - expected) / np.sqrt(variance / REPLICATIONS + 1e-12)
    assert z.max() < 4.5, (scheme, z.max())


@pytest.mark.parametrize("scheme", ["systematic", "residual"])
def test_low_variance_schemes_keep_integer_parts(scheme, log_weights):
    counts = offspring_counts(scheme, log_weights, jax.random.key(2))
    expected = NUM * np.exp(np.asarray(log_weights, np.float64) - jax.nn.logsumexp(log_weights))
    assert np.all(counts >= np.floor(expected - 1e-4))
    if scheme == "systematic":
        assert np.all(counts <= np.ceil(expected + 1e-4))


def test_multinomial_detected_as_higher_variance(log_weights):
    """Sanity of the harness: multinomial counts vary more than systematic ones."""
    multinomial = offspring_counts("multinomial", log_weights, jax.random.key(3)).var(axis=0).sum()
    systematic = offspring_counts("systematic", log_weights, jax.random.key(3)).var(axis=0).sum()
    assert systematic < 0.5 * multinomial


@pytest.mark.parametrize("scheme", sorted(RESAMPLING_SCHEMES))
def test_degenerate_and_tiny_weights(scheme):
    one_hot = jnp.full(NUM, -jnp.inf).at[7].set(0.0)
    indices = otf.resample_indices(jax.random.key(0), one_hot, scheme)
    assert np.all(np.asarray(indices) == 7)
    tiny = -1e4 + jnp.linspace(0.0, 5.0, NUM)  # exp() underflows to 0; the log domain does not
    indices = otf.resample_indices(jax.random.key(0), tiny, scheme)
    assert np.all((np.asarray(indices) >= 0) & (np.asarray(indices) < NUM))
    assert np.mean(np.asarray(indices) > NUM // 2) > 0.5  # the larger weights win


def test_unknown_scheme_is_rejected():
    with pytest.raises(ValueError, match="resampling"):
        otf.resample_indices(jax.random.key(0), jnp.zeros(4), "bogus")
    with pytest.raises(ValueError, match="resampling"):
        otf.sir(resampling="bogus")


@pytest.mark.parametrize("scheme", ["systematic", "residual"])
@pytest.mark.parametrize("num", [10, 1000])
def test_uniform_weights_keep_every_particle(scheme, num):
    """N w_i = 1 (0.99999994 after float32 rounding): each particle is kept exactly once."""
    indices = otf.resample_indices(jax.random.key(0), jnp.zeros(num), scheme)
    np.testing.assert_array_equal(np.sort(np.asarray(indices)), np.arange(num))


@pytest.mark.parametrize("num, num_active", [(7, None), (1000, None), (1_000_000, None),
                                             (1000, 637), (1000, 2), (1_000_000, 999_999)])
def test_linear_time_inversion_gives_the_binary_search_indices(num, num_active):
    # Stratified and systematic points are inverted in O(N) by strata; the ancestors must be
    # exactly the searchsorted ones, also with zero weights (flat stretches) and padding.
    from ot_filter.updates.resampling import _cdf, _invert_cdf, _invert_cdf_by_strata, _strata

    count = num if num_active is None else num_active
    key_w, key_zero, key_u = jax.random.split(jax.random.key(num + count), 3)
    weights = jax.random.exponential(key_w, (num,)) ** 3  # heavy-tailed: long steps and flats
    weights = jnp.where(jax.random.bernoulli(key_zero, 0.3, (num,)), 0.0, weights)
    weights = jnp.where(jnp.arange(num) < count, weights, 0.0)
    cdf = _cdf(weights)
    strata = _strata(num, num_active)
    # Offsets near 1 at large N: j + U rounds to j + 1 in float32, a point on the next stratum's
    # edge (the case the neighbouring-strata comparison is for).
    for offsets in (jax.random.uniform(key_u, (num,)), jnp.full((num,), 0.5), jnp.zeros(num),
                    jnp.full((num,), 0.99)):
        points = (strata + offsets[strata]) / count
        expected = _invert_cdf(cdf, points)
        got = _invert_cdf_by_strata(cdf, points, num_active)
        np.testing.assert_array_equal(got, expected)


def test_linear_time_inversion_of_nan_weights_matches_the_binary_search():
    # All log-weights -inf: NaN normalised weights. Both inversions must give the same indices
    # (the binary search puts every point before the NaNs: index 0), padded or not.
    from ot_filter.updates.resampling import _cdf, _invert_cdf, _invert_cdf_by_strata, _strata

    weights = jnp.full(5, jnp.nan)
    for num_active in (None, 3):
        count = 5 if num_active is None else num_active
        points = (_strata(5, num_active) + 0.5) / count
        np.testing.assert_array_equal(_invert_cdf_by_strata(_cdf(weights), points, num_active),
                                      _invert_cdf(_cdf(weights), points))
