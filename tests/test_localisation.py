"""Localisation: tapers, neighbour lists, the LETKF and the Schur-product EnKF.

Closed forms first: with a taper that reaches everything the LETKF is the global ETKF, and with
one that reaches only a coordinate's own observation it is n scalar ETKFs; the Schur-product
EnKF with a taper of 1 everywhere is the global perturbed EnKF under the same key.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ot_filter as otf
from ot_filter.filtering import _run_filter
from ot_filter.localisation import GASPARI_COHN_HALF_WIDTH, taper_weights


def _gaspari_cohn_reference(distance, c):
    """Gaspari & Cohn (1999) eq. (4.10), written out piece by piece."""
    z = np.abs(distance) / c
    out = np.zeros_like(z)
    inner = z <= 1
    outer = (z > 1) & (z < 2)
    zi, zo = z[inner], z[outer]
    out[inner] = -zi**5 / 4 + zi**4 / 2 + 5 * zi**3 / 8 - 5 * zi**2 / 3 + 1
    out[outer] = zo**5 / 12 - zo**4 / 2 + 5 * zo**3 / 8 + 5 * zo**2 / 3 - 5 * zo + 4 - 2 / (3 * zo)
    return out


def test_gaspari_cohn_taper_matches_the_closed_form_and_the_gaussian_near_zero(x64):
    radius = 3.0
    distance = np.linspace(0.0, 25.0, 2001)
    values = np.asarray(taper_weights(jnp.asarray(distance), radius, "gaspari_cohn"))
    c = GASPARI_COHN_HALF_WIDTH * radius
    np.testing.assert_allclose(values, _gaspari_cohn_reference(distance, c), atol=1e-12)
    assert np.all(values[distance >= 2 * c] == 0) and np.all(values[distance < 2 * c] > 0)
    assert np.all(np.diff(values) <= 1e-15)  # non-increasing
    small = distance[distance < 0.3 * radius]
    gaussian = np.exp(-0.5 * (small / radius) ** 2)
    # Second-order agreement: the error is O(r^3).
    assert np.max(np.abs(values[: small.size] - gaussian) / np.maximum((small / radius) ** 3, 1e-12)) < 1.0
    step = np.asarray(taper_weights(jnp.asarray(distance), radius, "step"))
    np.testing.assert_array_equal(step, (distance <= radius).astype(float))
    assert float(taper_weights(jnp.inf, radius, "gaspari_cohn")) == 0.0


def test_neighbour_lists_match_brute_force_on_periodic_points():
    rng = np.random.default_rng(0)
    state = rng.uniform(0, 10, size=(60, 2))
    observations = rng.uniform(0, 10, size=(35, 2))
    geometry = otf.points(state, observations, period=[10.0, np.inf])
    loc = otf.localisation(geometry, 1.0, taper="step")
    gaps = np.abs(state[:, None, :] - observations[None, :, :])
    gaps[..., 0] = np.minimum(gaps[..., 0], 10.0 - gaps[..., 0])
    dense = np.sqrt(np.sum(gaps**2, axis=-1))
    neighbours, distance = np.asarray(loc.neighbours), np.asarray(loc.neighbour_distances)
    assert neighbours.shape[1] == np.max(np.sum(dense <= 1.0, axis=1))
    for j in range(60):
        within = set(np.flatnonzero(dense[j] <= 1.0))
        listed = {int(i) for i, d in zip(neighbours[j], distance[j]) if np.isfinite(d)}
        assert listed == within
        finite = np.isfinite(distance[j])
        # Positions are stored in float32 (about 1e-6 absolute at 10).
        np.testing.assert_allclose(distance[j][finite], dense[j, neighbours[j][finite]], atol=1e-5)
    # A user metric gives the same lists as the built-in periodic Euclidean one.
    def metric(a, b):
        gap = jnp.abs(a - b)
        gap = gap.at[0].set(jnp.minimum(gap[0], 10.0 - gap[0]))
        return jnp.sqrt(jnp.sum(gap**2))

    custom = otf.localisation(otf.points(state, observations, metric=metric), 1.0, taper="step")
    np.testing.assert_allclose(custom.neighbour_distances, loc.neighbour_distances, rtol=1e-6)
    with pytest.raises(ValueError, match="max_radius"):
        otf.localisation(geometry, 2.0, max_radius=1.0)
    # Positions outside [0, period) are the same points.
    shifted = otf.points(state + np.array([30.0, 0.0]), observations - np.array([10.0, 0.0]),
                         period=[10.0, np.inf])
    again = otf.localisation(shifted, 1.0, taper="step")
    np.testing.assert_array_equal(again.neighbours, loc.neighbours)
    np.testing.assert_allclose(again.neighbour_distances, loc.neighbour_distances, atol=1e-5)


def _ensemble(seed, num, n, offset=2.0):
    return offset + jax.random.normal(jax.random.key(seed), (num, n)) * jnp.linspace(0.5, 2.0, n)


def test_letkf_reaching_everything_is_the_global_etkf(x64):
    model = otf.models.lorenz96(dim=10, observed=[0, 2, 3, 7, 9], observation_noise_std=0.8)
    particles = _ensemble(0, 6, 10)
    y = jnp.asarray(np.random.default_rng(1).normal(size=5))
    loc = otf.localisation(model.geometry, 100.0, taper="step")
    letkf = otf.letkf(loc, inflation=1.1)
    global_etkf = otf.enkf(inflation=1.1, perturbed=False)
    state = letkf.init(jax.random.key(0), particles, model)
    local, _, info = letkf.apply(jax.random.key(1), state, particles, y, model)
    reference, _, _ = global_etkf.apply(jax.random.key(1), state, particles, y, model)
    np.testing.assert_allclose(local, reference, rtol=0, atol=1e-10)
    assert float(info.local_observations) == 5.0
    # Batched over coordinates: the same numbers.
    batched, _, _ = otf.letkf(loc, inflation=1.1, batch_size=3).apply(
        jax.random.key(1), state, particles, y, model)
    np.testing.assert_allclose(batched, local, rtol=0, atol=1e-12)


def test_letkf_with_only_its_own_observation_is_n_scalar_etkfs(x64):
    n, num, std = 7, 5, 0.6
    model = otf.models.lorenz96(dim=n, observation_noise_std=std)
    particles = _ensemble(2, num, n)
    y = jnp.asarray(np.random.default_rng(3).normal(size=n))
    loc = otf.localisation(model.geometry, 0.5, taper="step")
    update = otf.letkf(loc)
    state = update.init(jax.random.key(0), particles)
    posterior, _, _ = update.apply(jax.random.key(0), state, particles, y, model)
    x = np.asarray(particles)
    for j in range(n):  # scalar ETKF: mean by the Kalman gain, anomalies shrunk by sqrt(R / (P + R))
        column = x[:, j]
        prior_var = column.var(ddof=1)
        gain = prior_var / (prior_var + std**2)
        mean = column.mean() + gain * (float(y[j]) - column.mean())
        anomalies = (column - column.mean()) * np.sqrt(std**2 / (prior_var + std**2))
        np.testing.assert_allclose(posterior[:, j], mean + anomalies, rtol=0, atol=1e-10)


def test_letkf_padded_particles_reproduce_the_unpadded_run(x64):
    model = otf.models.lorenz96(dim=12)
    _, observations = otf.simulate(jax.random.key(0), model, 15)
    update = otf.letkf(otf.localisation(model.geometry, 3.0), inflation=1.05)
    small = otf.run_filter(jax.random.key(1), model, update, observations, 6, save_every=0)
    padded = otf.run_filter(jax.random.key(1), model, update, observations, 10, save_every=0,
                            num_active=6)
    # Equal up to rounding (eigh of the padded Gram matrix), amplified by 15 chaotic cycles.
    np.testing.assert_allclose(padded.mean, small.mean, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(padded.spread, small.spread, rtol=1e-6, atol=1e-6)


def test_letkf_inflation_and_radius_vmap_in_one_program_without_retracing():
    model = otf.models.lorenz96(dim=16)
    _, observations = otf.simulate(jax.random.key(0), model, 20)
    geometry = model.geometry

    def run(inflation, radius):
        loc = otf.localisation(geometry, radius, max_radius=4.0)
        return otf.run_filter(jax.random.key(1), model, otf.letkf(loc, inflation=inflation),
                              observations, 8, save_every=0).mean

    inflations = jnp.asarray([1.0, 1.05, 1.1])
    radii = jnp.asarray([1.0, 2.5, 4.0])
    swept = jax.jit(jax.vmap(run))(inflations, radii)
    for i in range(3):
        single = otf.run_filter(
            jax.random.key(1), model,
            otf.letkf(otf.localisation(geometry, float(radii[i]), max_radius=4.0),
                      inflation=float(inflations[i])),
            observations, 8, save_every=0).mean
        np.testing.assert_allclose(swept[i], single, rtol=1e-4, atol=1e-4)
    size = _run_filter._cache_size()
    for radius in (1.5, 3.0):  # new values, same structure: no new program
        otf.run_filter(jax.random.key(1), model,
                       otf.letkf(otf.localisation(geometry, radius, max_radius=4.0)),
                       observations, 8, save_every=0)
    assert _run_filter._cache_size() == size


def test_schur_enkf_with_a_taper_of_one_is_the_global_perturbed_enkf(x64):
    model = otf.models.lorenz96(dim=10, observed=[1, 4, 5, 8])
    particles = _ensemble(4, 12, 10)
    y = jnp.asarray([0.5, -0.3, 1.2, 0.0])
    # Every coordinate and observation at one point: the taper is 1 everywhere.
    everything = otf.localisation(otf.points(np.zeros(10), np.zeros(4)), 1.0)
    local = otf.enkf(inflation=1.02, localisation=everything)
    state = local.init(jax.random.key(0), particles, model)
    a, _, _ = local.apply(jax.random.key(5), state, particles, y, model)
    b, _, _ = otf.enkf(inflation=1.02).apply(jax.random.key(5), state, particles, y, model)
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-10)
    # A short radius: coordinates out of every observation's reach do not move.
    near = otf.localisation(model.geometry, 0.25)  # support 0.91: its own observation only
    c, _, _ = otf.enkf(inflation=1.0, localisation=near).apply(jax.random.key(5), state, particles, y, model)
    untouched = np.setdiff1d(np.arange(10), [1, 4, 5, 8])
    np.testing.assert_allclose(c[:, untouched], particles[:, untouched], rtol=0, atol=1e-12)
    assert not np.allclose(c[:, [1, 4, 5, 8]], particles[:, [1, 4, 5, 8]])
    with pytest.raises(ValueError, match="letkf"):
        otf.enkf(perturbed=False, localisation=near)
    with pytest.raises(ValueError, match="gaspari_cohn"):  # the step taper's matrix is indefinite
        otf.enkf(localisation=otf.localisation(model.geometry, 0.5, taper="step"))
    with pytest.raises(ValueError, match="half the period"):
        otf.enkf(localisation=otf.localisation(model.geometry, 2.0))


def test_schur_enkf_gain_is_the_tapered_kalman_gain(x64):
    # The perturbed update is X + (y - h(X) - V) K^T: two observations under the same key (same
    # V) differ by (y1 - y2) K^T in every member, which recovers K exactly. It must be
    # (rho_xy o C_xh) (rho_yy o C_hh + R)^{-1}, with the Gaspari-Cohn tapers of the ring.
    n, observed, radius, std = 24, np.array([0, 3, 5, 9, 14, 20]), 1.5, 0.8
    model = otf.models.lorenz96(dim=n, observed=observed, observation_noise_std=std)
    particles = _ensemble(6, 15, n)
    update = otf.enkf(localisation=otf.localisation(model.geometry, radius))
    state = update.init(jax.random.key(0), particles, model)
    y = jnp.asarray(np.random.default_rng(4).normal(size=observed.size))
    first, _, _ = update.apply(jax.random.key(9), state, particles, y, model)
    directions = np.eye(observed.size)
    gain = np.stack([
        np.asarray(update.apply(jax.random.key(9), state, particles, y + direction, model)[0] - first)[0]
        for direction in directions], axis=1)  # [n, m]
    x = np.asarray(particles)
    anomalies = x - x.mean(axis=0)
    hx = anomalies[:, observed]
    cross = anomalies.T @ hx / (15 - 1)
    cov = hx.T @ hx / (15 - 1)

    def ring_distance(a, b):
        gap = np.abs(a[:, None] - b[None, :]) % n
        return np.minimum(gap, n - gap)

    def gaspari_cohn(d):
        return _gaspari_cohn_reference(d, GASPARI_COHN_HALF_WIDTH * radius)

    rho_xy = gaspari_cohn(ring_distance(np.arange(n), observed).astype(float))
    rho_yy = gaspari_cohn(ring_distance(observed, observed).astype(float))
    expected = (rho_xy * cross) @ np.linalg.inv(rho_yy * cov + std**2 * np.eye(observed.size))
    np.testing.assert_allclose(gain, expected, rtol=0, atol=1e-10)
    assert np.any(rho_xy == 0) and np.any((rho_xy > 0) & (rho_xy < 1))


@pytest.mark.long
def test_localisation_rescues_a_small_ensemble_on_lorenz96():
    # N = 10 members for n = 40 unknowns: the global square-root EnKF cannot span the error and
    # loses the truth; the LETKF (DAPPER's Sakov 2008 tuning) tracks it below the noise (std 1).
    model = otf.models.lorenz96()
    truth, observations = otf.simulate(jax.random.key(0), model, 400)
    burn = 100

    def rmse(update):
        result = otf.run_filter(jax.random.key(1), model, update, observations, 10, save_every=0)
        return float(jnp.mean(jnp.sqrt(jnp.mean((result.mean - truth) ** 2, axis=1))[burn:]))

    local = rmse(otf.letkf(otf.localisation(model.geometry, 4.0), inflation=1.04, rotate=True))
    global_ = rmse(otf.enkf(inflation=1.04, perturbed=False, rotate=True))
    assert local < 0.3, local
    assert global_ > 1.0, global_


def test_a_model_geometry_of_the_wrong_size_is_refused():
    model = otf.models.lorenz96(dim=8)
    wrong = model._replace(geometry=otf.ring(10))
    _, observations = otf.simulate(jax.random.key(0), model, 3)
    with pytest.raises(ValueError, match="model.geometry"):
        otf.run_filter(jax.random.key(1), wrong, otf.enkf(), observations, 8)
