"""Single Bayes-update properties with closed forms, degenerate cases and input checks."""

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ot_filter as otf
from conftest import random_linear_gaussian


def one_step_problem(num_particles=64, seed=0):
    A, Q, H, R, m0, P0 = random_linear_gaussian(seed)
    model = otf.models.linear_gaussian(A, Q, H, R, m0, P0)
    particles = jax.random.normal(jax.random.key(seed), (num_particles, 3)) * 1.3 + 0.5
    observation = jnp.array([0.7, -1.1])
    return model, particles, observation, (H, R)


def sample_moments(particles):
    particles = np.asarray(particles, np.float64)
    return particles.mean(axis=0), np.cov(particles.T)


def kalman_update(mean, cov, H, R, y):
    S = H @ cov @ H.T + R
    K = np.linalg.solve(S, H @ cov).T
    return mean + K @ (y - H @ mean), cov - K @ H @ cov


def assert_square_root_is_kalman_update(model, particles, y, H, R):
    """The ETKF posterior ensemble has exactly the Kalman update of the prior ensemble's moments."""
    update = otf.enkf(perturbed=False)
    posterior, _, info = update.apply(jax.random.key(1), update.init(None, particles), particles, y, model)
    mean, cov = sample_moments(particles)
    expected_mean, expected_cov = kalman_update(mean, cov, H, R, np.asarray(y))
    got_mean, got_cov = sample_moments(posterior)
    np.testing.assert_allclose(got_mean, expected_mean, atol=1e-10)
    np.testing.assert_allclose(got_cov, expected_cov, atol=1e-10)
    assert np.isfinite(info.innovation_condition)


def test_square_root_enkf_is_exact_kalman_update_of_ensemble_moments(x64):
    model, particles, y, (H, R) = one_step_problem()
    assert_square_root_is_kalman_update(model, particles, y, H, R)


def test_square_root_enkf_float32_close_to_float64():
    model, particles, y, (H, R) = one_step_problem()
    update = otf.enkf(perturbed=False)
    posterior, _, _ = update.apply(jax.random.key(1), update.init(None, particles), particles, y, model)
    mean, cov = sample_moments(particles)
    expected_mean, expected_cov = kalman_update(mean, cov, H, R, np.asarray(y, np.float64))
    got_mean, got_cov = sample_moments(posterior)
    np.testing.assert_allclose(got_mean, expected_mean, atol=2e-5)
    np.testing.assert_allclose(got_cov, expected_cov, atol=2e-5)


def test_perturbed_enkf_mean_is_exact_with_centred_perturbations(x64):
    model, particles, y, (H, R) = one_step_problem()
    update = otf.enkf()
    posterior, _, _ = update.apply(jax.random.key(2), update.init(None, particles), particles, y, model)
    mean, cov = sample_moments(particles)
    expected_mean, _ = kalman_update(mean, cov, H, R, np.asarray(y))
    np.testing.assert_allclose(sample_moments(posterior)[0], expected_mean, atol=1e-10)


@pytest.mark.long
def test_rotation_and_inflation(x64):
    model, particles, y, _ = one_step_problem()
    plain = otf.enkf(perturbed=False)
    rotated = otf.enkf(perturbed=False, rotate=True)
    state = plain.init(None, particles)
    a, _, _ = plain.apply(jax.random.key(3), state, particles, y, model)
    b, _, _ = rotated.apply(jax.random.key(3), state, particles, y, model)
    assert not np.allclose(a, b)  # members moved ...
    for got, want in zip(sample_moments(b), sample_moments(a)):  # ... moments kept exactly
        np.testing.assert_allclose(got, want, atol=1e-10)
    # Inflation = the plain update of the inflated prior.
    inflated = otf.enkf(inflation=1.3, perturbed=False)
    c, _, _ = inflated.apply(jax.random.key(3), state, particles, y, model)
    mean = particles.mean(axis=0)
    d, _, _ = plain.apply(jax.random.key(3), state, mean + 1.3 * (particles - mean), y, model)
    np.testing.assert_allclose(c, d, atol=1e-10)


def test_simulation_based_gain_with_singular_observation_covariance():
    """Cov(Y) singular (duplicated noiseless observation): regularised, finite, reported."""
    base = otf.models.squared_observation(dim=1)
    model = base._replace(
        sample_observation=lambda key, x: jnp.concatenate([x, x]),
        observation_function=None, observation_noise_cov=None, log_likelihood=None,
    )
    particles = jax.random.normal(jax.random.key(0), (100, 1))
    update = otf.enkf()
    posterior, _, info = update.apply(jax.random.key(1), update.init(None, particles), particles,
                                      jnp.array([0.5, 0.5]), model)
    assert np.all(np.isfinite(posterior))
    assert info.innovation_condition > 1e5  # flagged as (numerically) singular
    np.testing.assert_allclose(posterior, 0.5, atol=1e-2)  # noiseless: collapses on y


@pytest.mark.long
def test_sir_degenerate_weights_never_nan():
    model, particles, y, _ = one_step_problem()
    for bad in (-jnp.inf, jnp.nan):
        broken = model._replace(log_likelihood=lambda y, x, bad=bad: bad + 0.0 * x[0])
        update = otf.sir(jitter=0.5)
        state = update.init(None, particles)
        out, new_state, info = update.apply(jax.random.key(0), state, particles, y, broken)
        assert bool(info.degenerate)
        assert np.all(np.isfinite(out)) and np.all(np.isfinite(new_state.log_weights))
    # Astronomically small but finite likelihoods are fine: normalised in the log domain.
    tiny = model._replace(log_likelihood=lambda y, x: -1e30 - jnp.sum(x**2))
    out, new_state, info = otf.sir().apply(jax.random.key(0), state, particles, y, tiny)
    assert not bool(info.degenerate)
    assert np.all(np.isfinite(out)) and np.isfinite(info.ess)


class TestSirCarriesWeights(chex.TestCase):
    """The SIR update called eagerly and inside jax.jit (chex variants: __with_jit, __without_jit)."""

    @chex.variants(with_jit=True, without_jit=True)
    def test_sir_carries_weights_below_threshold(self):
        model, particles, y, _ = one_step_problem()
        update = otf.sir(ess_threshold=0.0)  # never resample
        state = update.init(None, particles)
        out, new_state, info = self.variant(update.apply)(jax.random.key(0), state, particles, y, model)
        assert not bool(info.resampled)
        np.testing.assert_array_equal(out, particles)
        expected = jax.vmap(model.log_likelihood, (None, 0))(y, particles)
        expected = expected - jax.nn.logsumexp(expected)
        np.testing.assert_allclose(new_state.log_weights, expected, atol=1e-5)
        np.testing.assert_allclose(info.ess, otf.metrics.ess(expected), rtol=1e-5)


@pytest.mark.long
def test_sir_jitter_adds_the_documented_covariance():
    """Flat likelihood: resampling keeps Cov = C; jitter adds (jitter * N^(-1/(n+4)))^2 C."""
    num = 200_000
    particles = jax.random.normal(jax.random.key(0), (num, 2)) @ jnp.array([[1.0, 0.0], [0.6, 0.8]])
    model = otf.models.squared_observation(dim=2)._replace(log_likelihood=lambda y, x: 0.0 * x[0])
    jitter = 2.0
    update = otf.sir(jitter=jitter)
    out, _, _ = update.apply(jax.random.key(1), update.init(None, particles), particles, jnp.zeros(2), model)
    factor = 1.0 + (jitter * num ** (-1.0 / 6.0)) ** 2
    expected = factor * np.cov(np.asarray(particles, np.float64).T)
    # Standard error of a covariance entry ~ sqrt(2 / N) * scale; 5 of them.
    np.testing.assert_allclose(np.cov(np.asarray(out, np.float64).T), expected, atol=5 * np.sqrt(2 / num) * 2)


def test_builders_reject_bad_configuration():
    with pytest.raises(ValueError, match="inflation"):
        otf.enkf(inflation=0.9)
    with pytest.raises(ValueError, match="ess_threshold"):
        otf.sir(ess_threshold=1.5)
    with pytest.raises(ValueError, match="jitter"):
        otf.sir(jitter=-1.0)


def test_updates_reject_models_they_cannot_handle():
    model, particles, y, _ = one_step_problem()
    no_likelihood = model._replace(log_likelihood=None)
    with pytest.raises(ValueError, match="log_likelihood"):
        otf.sir().apply(jax.random.key(0), otf.sir().init(None, particles), particles, y, no_likelihood)
    no_gaussian = model._replace(observation_noise_cov=None)
    update = otf.enkf(perturbed=False)
    with pytest.raises(ValueError, match="observation_noise_cov"):
        update.apply(jax.random.key(0), update.init(None, particles), particles, y, no_gaussian)
    big = jnp.zeros((5000, 3))
    with pytest.raises(ValueError, match="rotate"):
        otf.enkf(rotate=True).apply(jax.random.key(0), None, big, y, model)


@pytest.mark.long
def test_random_rotation_is_haar_on_the_complement_of_ones(x64):
    """O = rotation(C) + 11^T/N for the centring matrix C. Checks O O^T = I and O 1 = 1, and for
    the block Q acting on the complement (in the basis of the Householder reflection P): the
    Haar moments E[Q] = 0, E[Q_ij^2] = 1/d, E[Q_ij^4] = 3/(d(d+2)), d = N - 1 (5 std errors)."""
    from ot_filter.updates.enkf import random_rotation

    num, draws = 6, 4000
    centring = jnp.eye(num) - 1.0 / num
    ones = jnp.ones((num, num)) / num
    rotations = jax.vmap(lambda k: random_rotation(k, centring) + ones)(
        jax.random.split(jax.random.key(0), draws)
    )
    np.testing.assert_allclose(rotations @ jnp.swapaxes(rotations, 1, 2), np.broadcast_to(np.eye(num), rotations.shape), atol=1e-10)
    np.testing.assert_allclose(rotations.sum(axis=2), 1.0, atol=1e-10)
    direction = np.eye(num)[0] - 1.0 / np.sqrt(num)
    direction /= np.linalg.norm(direction)
    reflection = np.eye(num) - 2 * np.outer(direction, direction)
    blocks = np.einsum("ij,bjk,kl->bil", reflection, np.asarray(rotations), reflection)[:, 1:, 1:]
    d = num - 1
    for power, expected in ((1, 0.0), (2, 1.0 / d), (4, 3.0 / (d * (d + 2)))):
        values = blocks**power
        error = np.abs(values.mean(axis=0) - expected)
        np.testing.assert_array_less(error, 5 * values.std(axis=0) / np.sqrt(draws) + 1e-12)


@pytest.mark.parametrize("num_particles", [4, 10, 11, 30])
def test_square_root_enkf_exact_in_both_gram_branches(x64, num_particles):
    """m = 10 observations: N <= m uses the N x N Gram matrix, N > m the m x m one."""
    rng = np.random.default_rng(num_particles)
    H = rng.normal(size=(10, 3))
    R = np.diag(rng.uniform(0.5, 2.0, size=10))
    model = otf.models.linear_gaussian(0.9 * np.eye(3), 0.1 * np.eye(3), H, R, np.zeros(3), np.eye(3))
    particles = jnp.asarray(rng.normal(size=(num_particles, 3)))
    y = jnp.asarray(rng.normal(size=10))
    assert_square_root_is_kalman_update(model, particles, y, H, R)


@pytest.mark.long
def test_simulation_based_gain_with_fewer_particles_than_observations():
    """N = 12 <= m = 40: Cov(Y) is singular; the pseudo-inverse update matches float64 NumPy."""
    rng = np.random.default_rng(0)
    H = rng.normal(size=(40, 3))
    model = otf.StateSpaceModel(
        sample_initial=lambda key: jnp.zeros(3),
        sample_transition=lambda key, x: x,
        sample_observation=lambda key, x: jnp.asarray(H, x.dtype) @ x + 0.3 * jax.random.normal(key, (40,)),
    )
    particles = jnp.asarray(rng.normal(size=(12, 3)), jnp.float32)
    y = jnp.asarray(rng.normal(size=40), jnp.float32)
    update = otf.enkf()
    key = jax.random.key(1)
    posterior, _, info = update.apply(key, update.init(None, particles), particles, y, model)
    simulated = np.asarray(jax.vmap(model.sample_observation)(jax.random.split(jax.random.split(key)[0], 12), particles), np.float64)
    x = np.asarray(particles, np.float64)
    xa, ya = x - x.mean(0), simulated - simulated.mean(0)
    gain = (xa.T @ ya / 11) @ np.linalg.pinv(ya.T @ ya / 11, rcond=1e-5)
    expected = x + (np.asarray(y, np.float64) - simulated) @ gain.T
    np.testing.assert_allclose(posterior, expected, rtol=2e-3, atol=2e-3)
    assert info.innovation_condition > 1e6  # reported as (numerically) singular


def test_collapsed_ensemble_with_deterministic_simulator_is_left_alone():
    model = otf.StateSpaceModel(
        sample_initial=lambda key: jnp.zeros(2),
        sample_transition=lambda key, x: x,
        sample_observation=lambda key, x: x**2,
    )
    particles = jnp.ones((20, 2))
    update = otf.enkf()
    posterior, _, _ = update.apply(jax.random.key(0), update.init(None, particles), particles, jnp.array([4.0, 0.0]), model)
    np.testing.assert_array_equal(posterior, particles)


def test_sir_jitter_revives_a_collapsed_ensemble():
    """All the weight on one particle: the jitter falls back to the equally weighted covariance
    (as DAPPER), so resampled copies are spread out instead of collapsing for good."""
    model, particles, _, _ = one_step_problem(num_particles=200)
    y = jnp.array([400.0, 400.0])  # far out: one particle takes all the mass
    update = otf.sir(jitter=0.5)
    out, _, info = update.apply(jax.random.key(0), update.init(None, particles), particles, y, model)
    assert float(info.ess) < 1.0 + 1e-3
    assert len(np.unique(np.asarray(out)[:, 0])) == 200
    assert float(otf.metrics.spread(out)) > 0.05


def test_sir_jitter_covariance_uses_the_weights():
    """The regularisation noise has covariance (jitter * N^(-1/(n+4)))^2 C_w, C_w weighted."""
    from ot_filter.updates.sir import _regularisation_noise

    num = 200_000
    particles = jax.random.normal(jax.random.key(0), (num, 2)) @ jnp.array([[1.0, 0.0], [0.6, 0.8]])
    log_weights = -0.5 * jnp.sum((particles - jnp.array([1.0, -0.5])) ** 2, axis=1)  # non-uniform
    noise = _regularisation_noise(jax.random.key(1), particles, log_weights, 2.0)
    weights = np.exp(np.asarray(log_weights, np.float64))
    weights /= weights.sum()
    x = np.asarray(particles, np.float64)
    anomalies = x - weights @ x
    weighted = (anomalies.T * weights) @ anomalies / (1 - np.sum(weights**2))
    expected = (2.0 * num ** (-1.0 / 6.0)) ** 2 * weighted
    np.testing.assert_allclose(np.cov(np.asarray(noise, np.float64).T), expected, atol=5 * np.sqrt(2 / num) * np.abs(expected).max())


@pytest.mark.parametrize("perturbed", [True, False])
def test_enkf_with_precomputed_noise_factors_is_the_same_update(x64, perturbed):
    # run_filter factors R once (model.observation_noise_factors); the update must not change.
    model, particles, y, (H, R) = one_step_problem()
    prepared = otf.model.with_observation_noise_factors(model)
    chol, inverse = prepared.observation_noise_factors
    np.testing.assert_allclose(chol @ chol.T, R, atol=1e-12)
    np.testing.assert_allclose(inverse @ chol, np.eye(2), atol=1e-12)
    update = otf.enkf(perturbed=perturbed)
    state = update.init(None, particles)
    direct, _, _ = update.apply(jax.random.key(1), state, particles, y, model)
    cached, _, _ = update.apply(jax.random.key(1), state, particles, y, prepared)
    np.testing.assert_allclose(cached, direct, atol=1e-12)


def test_float32_noise_covariance_is_factored_in_the_filter_precision(x64):
    model, _, _, (H, R) = one_step_problem()
    model = model._replace(observation_noise_cov=jnp.asarray(R, jnp.float32))
    chol, inverse = otf.model.with_observation_noise_factors(model, jnp.float64).observation_noise_factors
    assert chol.dtype == inverse.dtype == jnp.float64
    R32 = np.asarray(np.float32(R), np.float64)
    np.testing.assert_allclose(chol @ chol.T, R32, atol=1e-13)
