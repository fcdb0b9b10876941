"""Padded particle axis: num_active of N_max particles are real, the rest is padding (log-weight
-inf, see ot_filter.updates.base). Padding values must not matter, a padded run must be the
unpadded run with the same key (jax.random streams are prefix-consistent), SIR with a mask must
still match the Kalman filter, one compiled program must serve every count (vmap), and bad
counts must be rejected. (Runs without num_active are what the other test files check.)

Compilation dominates the cost of these tests (about 2 s per filter on 2 cores), so a compiled
program serves several checks: run_filter's jit cache shares it between calls with the same
update object, shapes and options (initial particles and num_active are traced)."""

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ot_filter as otf
from conftest import random_linear_gaussian
from ot_filter.updates.base import uniform_log_weights
from ot_filter.updates.enkf import random_rotation

NUM_STEPS = 5
NUM_PARTICLES, NUM_ACTIVE = 200, 50
SIR = otf.sir(ess_threshold=0.3, jitter=0.3)
ENKF = otf.enkf(inflation=1.1)


def initial_draws(parameters, num, rng):
    _, _, _, _, m0, P0 = parameters
    return jnp.asarray(rng.multivariate_normal(m0, P0, size=num), jnp.float32)


@pytest.fixture(scope="module")
def setup():
    """The linear-Gaussian model, T = 5 observations and 200 draws from its prior (simulated
    with NumPy: no compilation)."""
    parameters = random_linear_gaussian(5)
    A, Q, H, R, m0, P0 = parameters
    rng = np.random.default_rng(5)
    state = rng.multivariate_normal(m0, P0)
    observations = []
    for _ in range(NUM_STEPS):
        state = A @ state + rng.multivariate_normal(np.zeros(3), Q)
        observations.append(H @ state + rng.multivariate_normal(np.zeros(2), R))
    model = otf.models.linear_gaussian(*parameters)
    return model, jnp.asarray(np.array(observations), jnp.float32), initial_draws(parameters, NUM_PARTICLES, rng)


def padded(start, num_active, fill):
    """``start`` with the rows from num_active on replaced: 'copies' of active rows, or a number."""
    rows = np.arange(num_active, start.shape[0])
    if fill == "copies":
        return start.at[rows].set(start[rows % num_active])
    return start.at[rows].set(fill)


def assert_padding_contract(particles, log_weights, num_active):
    """Padding at -inf, active weights normalised and finite, active particles finite."""
    log_weights = np.asarray(log_weights)
    assert np.all(np.isneginf(log_weights[..., num_active:]))
    assert np.all(np.isfinite(log_weights[..., :num_active]))
    np.testing.assert_allclose(jax.nn.logsumexp(log_weights, axis=-1), 0.0, atol=1e-5)
    assert np.all(np.isfinite(particles)) and np.all(np.abs(particles[..., :num_active, :]) < 100)


@pytest.mark.parametrize("update", [SIR, ENKF], ids=["sir_ess_jitter", "enkf_inflation"])
def test_padding_values_do_not_matter_in_run_filter(setup, update):
    """Padding holding copies of active particles or 1e3: the same active particles, weights,
    mean, spread and info at every step (one compiled program for both)."""
    model, observations, start = setup
    results = [
        otf.run_filter(jax.random.key(2), model, update, observations, NUM_PARTICLES,
                       initial_particles=padded(start, NUM_ACTIVE, fill), num_active=NUM_ACTIVE)
        for fill in ("copies", 1e3)
    ]
    first, second = ((r.mean, r.spread, r.particles[:, :NUM_ACTIVE], r.log_weights, r.info) for r in results)
    chex.assert_trees_all_close(first, second, rtol=1e-6, atol=1e-6)
    # The 1e3 padding is replaced by copies of the draws at SIR's first resampling, by the
    # posterior mean at every EnKF update.
    resampled = np.asarray(getattr(results[1].info, "resampled", np.ones(NUM_STEPS, bool)))
    assert np.any(resampled) and (update is ENKF or not np.all(resampled))
    for result in results:
        assert_padding_contract(result.particles, result.log_weights, NUM_ACTIVE)
        assert np.all(np.abs(result.particles[np.argmax(resampled):]) < 100)


def test_simulation_based_enkf_ignores_padding(setup):
    """One update (Cov(X, Y), Cov(Y) from simulated pairs) of 30 active particles among 40:
    padding (copies or 1e3) does not change the active result and comes out at -inf and at the
    posterior mean. (Its k - 1 divisors are the exact-R variant's, checked against the unpadded
    run in test_padded_run_is_the_unpadded_run; the square root and the rotation in
    test_square_root_transform_of_the_active_block_is_exact.)"""
    model, observations, start = setup
    model = model._replace(observation_function=None, observation_noise_cov=None)
    update = otf.enkf()
    num, num_active = 40, 30
    log_weights = uniform_log_weights(start[:num], num_active)

    @jax.jit
    def apply(particles, log_weights):
        state = otf.updates.UniformWeightsState(log_weights)
        return update.apply(jax.random.key(3), state, particles, observations[0], model)

    (first, first_state, first_info), (second, second_state, second_info) = (
        apply(padded(start[:num], num_active, fill), log_weights) for fill in ("copies", 1e3))
    np.testing.assert_allclose(first[:num_active], second[:num_active], rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(first_info.innovation_condition, second_info.innovation_condition, rtol=1e-6)
    for out, out_state in ((first, first_state), (second, second_state)):
        assert_padding_contract(out, out_state.log_weights, num_active)
        assert np.all(np.abs(out) < 100)
        np.testing.assert_allclose(out[num_active:], np.broadcast_to(
            out[:num_active].mean(axis=0), (num - num_active, 3)), atol=1e-5)


@pytest.mark.parametrize("update", [SIR, ENKF], ids=["sir_ess_jitter", "enkf_inflation"])
def test_padded_run_is_the_unpadded_run(setup, update):
    """num_active = 50 of 200 and a plain run with N = 50, same key: jax.random streams are
    prefix-consistent (jax_threefry_partitionable), so the propagation noises, perturbations,
    resampling uniforms and jitter of the first 50 particles are the same, and the comb has 50
    teeth, the ESS threshold and jitter bandwidth use 50: equal up to float32 rounding."""
    assert jax.config.jax_threefry_partitionable
    model, observations, start = setup
    padded_run = otf.run_filter(jax.random.key(2), model, update, observations, NUM_PARTICLES,
                                initial_particles=padded(start, NUM_ACTIVE, "copies"),
                                num_active=NUM_ACTIVE)
    plain = otf.run_filter(jax.random.key(2), model, update, observations, NUM_ACTIVE,
                           initial_particles=start[:NUM_ACTIVE])
    np.testing.assert_allclose(padded_run.mean, plain.mean, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(padded_run.spread, plain.spread, rtol=1e-5)
    np.testing.assert_allclose(padded_run.particles[:, :NUM_ACTIVE], plain.particles, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(padded_run.log_weights[:, :NUM_ACTIVE], plain.log_weights, rtol=1e-5, atol=1e-5)
    chex.assert_trees_all_close(padded_run.info, plain.info, rtol=1e-4)
    if update is SIR:
        assert np.any(plain.info.resampled) and not np.all(plain.info.resampled)


def test_sir_with_mask_matches_kalman(setup):
    """k = 2000 of N_max = 3000, padding at 50 (a leak would show), stratified resampling
    triggered by the ESS: the weighted mean over the active particles is the Kalman mean within
    Monte-Carlo error (a filter mean's error is up to ~3x the iid sqrt(P / ESS), measured in
    test_particle_filters_vs_kalman; 6 of those), padding stays at -inf, nothing is NaN."""
    model, observations, _ = setup
    num_particles, num_active = 3000, 2000
    update = otf.sir(resampling="stratified", ess_threshold=0.5)
    start = initial_draws(random_linear_gaussian(5), num_particles, np.random.default_rng(6))

    result = otf.run_filter(jax.random.key(7), model, update, observations, num_particles,
                            initial_particles=start.at[num_active:].set(50.0), num_active=num_active)
    exact = otf.kalman_filter(model, observations)
    ess = np.asarray(result.info.ess)
    assert np.all(ess <= num_active * (1 + 1e-5)) and np.any(result.info.resampled)
    variance = np.diagonal(np.asarray(exact.cov), axis1=1, axis2=2)
    np.testing.assert_array_less(np.abs(result.mean - exact.mean), 6 * 3 * np.sqrt(variance / ess[:, None]))
    weights = np.exp(np.asarray(result.log_weights, np.float64))
    np.testing.assert_allclose(np.einsum("tk,tki->ti", weights, result.particles), result.mean, atol=1e-4)
    assert_padding_contract(result.particles, result.log_weights, num_active)
    for leaf in [result.spread, *jax.tree.leaves(result.info)]:
        assert not np.any(np.isnan(leaf))


def test_vmap_over_num_active_matches_separate_calls(setup):
    """One jitted program vmapped over num_active: the same results as separate calls with the
    same key (which share one compiled program too), to the last ulp or so (a batched program
    rounds its fused arithmetic differently; same resampling decisions); a traced count out of
    range gives NaN."""
    model, observations, start = setup
    initial = padded(start, NUM_ACTIVE, "copies")

    def run(count):
        return otf.run_filter(jax.random.key(8), model, SIR, observations, NUM_PARTICLES,
                              initial_particles=initial, num_active=count)

    counts = [50, 100, 200, 1, 201]
    sweep = jax.jit(jax.vmap(run))(jnp.array(counts))
    for i, count in enumerate(counts[:3]):
        single = run(count)
        chex.assert_trees_all_close(jax.tree.map(lambda leaf: leaf[i], sweep[:4]), single[:4],
                                    rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(sweep.particles[i, :, :count], single.particles[:, :count], rtol=1e-6, atol=1e-6)
    assert np.all(np.isfinite(sweep.mean[:3]))
    assert np.all(np.isnan(sweep.mean[3:])) and np.all(np.isnan(sweep.spread[3:]))


def test_bad_num_active_is_rejected(setup):
    model, observations, _ = setup
    key, update = jax.random.key(0), otf.enkf()
    for bad in (0, 1, 11, jnp.array(1), np.int64(-3)):
        with pytest.raises(ValueError, match="num_active"):
            otf.run_filter(key, model, update, observations, 10, num_active=bad)
    for bad in (2.5, True, jnp.array([3, 4]), jnp.array(3.0)):
        with pytest.raises(TypeError, match="num_active"):
            otf.run_filter(key, model, update, observations, 10, num_active=bad)


def etkf_reference(particles, H, R, y):
    """The k-particle ETKF with the symmetric square root, in NumPy: posterior particles and the
    largest eigenvalue of I + S S^T."""
    k = particles.shape[0]
    mean = particles.mean(axis=0)
    anomalies = particles - mean
    predicted = particles @ H.T
    whitening = np.linalg.inv(np.linalg.cholesky(R))
    S = (predicted - predicted.mean(axis=0)) @ whitening.T / np.sqrt(k - 1)
    d = whitening @ (y - predicted.mean(axis=0))
    gram = np.eye(k) + S @ S.T
    eigenvalues, eigenvectors = np.linalg.eigh(gram)
    inverse_sqrt = eigenvectors @ np.diag(eigenvalues**-0.5) @ eigenvectors.T
    posterior_mean = mean + anomalies.T @ np.linalg.solve(gram, S @ d) / np.sqrt(k - 1)
    return posterior_mean + inverse_sqrt @ anomalies, eigenvalues.max()


def test_square_root_transform_of_the_active_block_is_exact(x64):
    """ETKF with zero anomaly rows for padding (values 7), k = 6 active, m = 10 observations: the
    active block gets exactly the k-particle transform and sqrt(k - 1) scaling (N_max = 9 <= m:
    the N x N Gram branch) with the same conditioning diagnostic. With rotate=True and
    N_max = 30 (the m x m branch, k - 1 < m) the active block has exactly those moments and
    padding values (7 or -1e3) do not matter."""
    rng = np.random.default_rng(0)
    H = rng.normal(size=(10, 3))
    R = np.diag(rng.uniform(0.5, 2.0, size=10))
    model = otf.models.linear_gaussian(0.9 * np.eye(3), 0.1 * np.eye(3), H, R, np.zeros(3), np.eye(3))
    y = rng.normal(size=10)
    num_active = 6
    active = rng.normal(size=(num_active, 3))
    expected, largest = etkf_reference(active, H, R, y)

    def padded_state(num_particles, fill):
        particles = jnp.asarray(np.concatenate([active, np.full((num_particles - num_active, 3), fill)]))
        return particles, otf.updates.UniformWeightsState(uniform_log_weights(particles, num_active))

    update = otf.enkf(perturbed=False)
    particles, state = padded_state(9, 7.0)
    posterior, new_state, info = jax.jit(update.apply)(jax.random.key(0), state, particles, jnp.asarray(y), model)
    np.testing.assert_allclose(posterior[:num_active], expected, atol=1e-10)
    np.testing.assert_allclose(posterior[num_active:], np.broadcast_to(expected.mean(axis=0), (3, 3)), atol=1e-10)
    np.testing.assert_allclose(info.innovation_condition, largest, rtol=1e-8)
    np.testing.assert_array_equal(new_state.log_weights, state.log_weights)

    rotate = jax.jit(otf.enkf(perturbed=False, rotate=True).apply)
    (first, _, first_info), (second, _, second_info) = (
        rotate(jax.random.key(1), *padded_state(30, fill)[::-1], jnp.asarray(y), model)
        for fill in (7.0, -1e3))
    np.testing.assert_allclose(first, second, atol=1e-12)
    got = np.asarray(first[:num_active])
    assert not np.allclose(got, expected, atol=1e-3)  # members moved ...
    np.testing.assert_allclose(got.mean(axis=0), expected.mean(axis=0), rtol=0, atol=1e-10)  # ... moments kept
    np.testing.assert_allclose(np.cov(got.T), np.cov(expected.T), rtol=0, atol=1e-10)
    np.testing.assert_allclose(first[num_active:], np.broadcast_to(expected.mean(axis=0), (24, 3)),
                               rtol=0, atol=1e-10)
    # The rotated square root factors by Cholesky: its diagnostic is a lower bound.
    assert 1.0 <= first_info.innovation_condition <= largest * (1 + 1e-8)


def test_masked_rotation_is_haar_on_the_active_block():
    """k = 6 of N = 8: O acts on the first k rows as a Haar rotation fixing the k-vector of ones
    (the moments of test_updates' Haar test at d = k - 1) and leaves the padding rows at 0."""
    num, num_active, draws = 8, 6, 4000
    centring = jnp.zeros((num, num_active)).at[:num_active].set(jnp.eye(num_active) - 1.0 / num_active)
    rotated = jax.jit(lambda keys: jax.lax.map(
        lambda k: random_rotation(k, centring, jnp.asarray(num_active)), keys))(
        jax.random.split(jax.random.key(0), draws))
    np.testing.assert_array_equal(rotated[:, num_active:], 0.0)
    rotations = np.asarray(rotated[:, :num_active], np.float64) + 1.0 / num_active
    np.testing.assert_allclose(rotations @ np.swapaxes(rotations, 1, 2),
                               np.broadcast_to(np.eye(num_active), rotations.shape), atol=1e-5)
    np.testing.assert_allclose(rotations.sum(axis=2), 1.0, atol=1e-5)
    direction = np.eye(num_active)[0] - 1.0 / np.sqrt(num_active)
    direction /= np.linalg.norm(direction)
    reflection = np.eye(num_active) - 2 * np.outer(direction, direction)
    blocks = np.einsum("ij,bjk,kl->bil", reflection, rotations, reflection)[:, 1:, 1:]
    d = num_active - 1
    for power, expected in ((1, 0.0), (2, 1.0 / d), (4, 3.0 / (d * (d + 2)))):
        values = blocks**power
        error = np.abs(values.mean(axis=0) - expected)
        np.testing.assert_array_less(error, 5 * values.std(axis=0) / np.sqrt(draws) + 1e-5)


def test_resampling_draws_among_active_with_num_active_teeth():
    """30 active of 50 (padding -inf), num_active traced: for every scheme E[count_i] = k w_i
    over the first k slots, padding never drawn, slot j >= k repeats slot j mod k; systematic
    keeps floor/ceil of k w_i, residual at least floor(k w_i)."""
    schemes = ["multinomial", "stratified", "systematic", "residual"]
    num, num_active, replications = 50, 30, 4000
    rng = np.random.default_rng(0)
    raw = rng.exponential(size=num_active) ** 3
    raw[3] = 5.0 * raw.sum() / num_active
    log_weights = jnp.full(num, -jnp.inf).at[:num_active].set(jnp.log(jnp.asarray(raw / raw.sum(), jnp.float32)))
    keys = jax.random.split(jax.random.key(1), replications)
    draws = jax.jit(jax.vmap(lambda k, a: [otf.resample_indices(k, log_weights, scheme, num_active=a)
                                           for scheme in schemes], (0, None)))(keys, num_active)
    for scheme, indices in zip(schemes, draws):
        check_offspring(scheme, np.asarray(indices), raw, num_active)
    with pytest.raises(ValueError, match="num_active"):
        otf.resample_indices(keys[0], log_weights, "systematic", num_active=num + 1)


def check_offspring(scheme, indices, raw, num_active):
    replications, num = indices.shape
    assert np.all(indices < num_active)
    np.testing.assert_array_equal(indices[:, num_active:], indices[:, np.arange(num_active, num) % num_active])
    counts = np.stack([np.bincount(row[:num_active], minlength=num_active) for row in indices])
    expected = num_active * raw / raw.sum()
    fraction = expected - np.floor(expected)
    variance = np.maximum(counts.var(axis=0, ddof=1), fraction * (1 - fraction))
    z = np.abs(counts.mean(axis=0) - expected) / np.sqrt(variance / replications + 1e-12)
    assert z.max() < 4.5, (scheme, z.max())
    if scheme in ("systematic", "residual"):
        assert np.all(counts >= np.floor(expected - 1e-4)), scheme
    if scheme == "systematic":
        assert np.all(counts <= np.ceil(expected + 1e-4))


def test_spread_ignores_padding_also_when_collapsed():
    """metrics.spread with -inf padding: the weighted spread of the active particles; with all
    the mass on one particle, the equally weighted fallback is over the active ones only."""
    rng = np.random.default_rng(0)
    particles = np.concatenate([rng.normal(size=(5, 2)), np.full((3, 2), 1e3)]).astype(np.float32)
    expected = np.sqrt(np.mean(np.var(particles[:5].astype(np.float64), axis=0, ddof=1)))
    uniform = np.array([-np.log(5.0)] * 5 + [-np.inf] * 3, np.float32)
    collapsed = np.array([0.0, -1e4, -1e4, -1e4, -1e4] + [-np.inf] * 3, np.float32)
    spreads = jax.jit(jax.vmap(otf.metrics.spread, (None, 0)))(particles, np.stack([uniform, collapsed]))
    np.testing.assert_allclose(spreads, [expected, expected], rtol=1e-5)
