"""Shared fixtures: random linear-Gaussian models (built in the caller's precision), the dense
reference of the OT update's EnKF fallback."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    """Drops JAX's compiled programs after each test module. Every CPU executable holds about 18
    memory mappings until its cache entry goes, and a test worker that compiles a few thousand
    programs reaches the kernel's limit (vm.max_map_count, 65,530) and segfaults. Three runs lost
    a worker late in the suite; the one whose traceback we have died inside XLA's compiler, and a
    surviving worker held 34,000 mappings near the end. ``jax.clear_caches`` unmaps them (300
    small programs: 5,952 mappings, 518 after it)."""
    yield
    jax.clear_caches()


def random_linear_gaussian(seed: int, state_dim: int = 3, observation_dim: int = 2):
    """A stable random linear-Gaussian model; matrices drawn with NumPy (float64)."""
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(state_dim, state_dim))
    A *= 0.9 / np.max(np.abs(np.linalg.eigvals(A)))  # spectral radius 0.9
    B = rng.normal(size=(state_dim, state_dim))
    Q = 0.3 * B @ B.T / state_dim + 0.05 * np.eye(state_dim)
    H = rng.normal(size=(observation_dim, state_dim))
    C = rng.normal(size=(observation_dim, observation_dim))
    R = 0.5 * C @ C.T / observation_dim + 0.2 * np.eye(observation_dim)
    m0 = rng.normal(size=state_dim)
    D = rng.normal(size=(state_dim, state_dim))
    P0 = D @ D.T / state_dim + 0.1 * np.eye(state_dim)
    return (A, Q, H, R, m0, P0)


def perturbed_enkf_reference(particles, simulated, observation, scaling, active=None, model=None):
    """Dense float64 reference of the OT update's fallback: X^i + K (y - Y^i) with the update's
    own simulated observations Y^i, from the standardised pairs of the active rows (divisor
    k - 1), a missing (NaN) component of y held at its standardised mean 0 in every pair, padding
    rows at the active rows' posterior mean. K = Cov(X, h) (Cov(h) + R)^-1 with the ``model``'s
    h and R (standardised) when it has additive Gaussian noise; else (or without ``model``)
    K = Cov(X, Y) (Cov(Y) + r I)^-1 with the relative ridge r = 1e-4 (1 + tr Cov(Y) / m)."""
    active = np.ones(len(particles), bool) if active is None else np.asarray(active)
    observed = np.isfinite(np.asarray(observation))
    xs = np.asarray(scaling.standardise_x(particles), np.float64)
    ys = np.where(observed, np.asarray(scaling.standardise_y(simulated), np.float64), 0.0)
    y = np.where(observed, np.asarray(scaling.standardise_y(observation), np.float64), 0.0)
    y_scale = np.asarray(scaling.y_scale, np.float64)
    xa = xs[active] - xs[active].mean(axis=0)
    if model is not None and model.has_gaussian_observation_noise:
        h = np.stack([np.asarray(model.observation_function(jnp.asarray(x)), np.float64) for x in np.asarray(particles)])
        hs = np.where(observed, (h - np.asarray(scaling.y_mean, np.float64)) / y_scale, 0.0)
        ha = hs[active] - hs[active].mean(axis=0)
        noise = np.asarray(model.observation_noise_cov, np.float64)
        noise = np.diag(noise) if noise.ndim == 1 else noise
        noise = np.where(np.outer(observed, observed), noise / np.outer(y_scale, y_scale), np.eye(len(observed)))
        cross, cov_y = xa.T @ ha / (active.sum() - 1), ha.T @ ha / (active.sum() - 1) + noise
    else:
        ya = ys[active] - ys[active].mean(axis=0)
        cross, cov_y = xa.T @ ya / (active.sum() - 1), ya.T @ ya / (active.sum() - 1)
        cov_y = cov_y + 1e-4 * (1 + np.trace(cov_y) / cov_y.shape[0]) * np.eye(cov_y.shape[0])
    moved = xs + (y - ys) @ np.linalg.solve(cov_y, cross.T)
    moved = np.where(active[:, None], moved, moved[active].mean(axis=0))
    return np.asarray(scaling.restore_x(jnp.asarray(moved, jnp.float32)))


@pytest.fixture
def x64():
    """Runs the test body with float64 enabled."""
    with jax.enable_x64(True):
        yield


def assert_gaussian_posterior(update, state, particles, posterior, mean_tol, var_range):
    """The 1-D Gaussian check of a learned conditional map: Y = X + N(0, 1), the map trained at
    y = 2 gave ``posterior``; the exact posterior given the particles' own moments (m, v) is
    N(v' (m / v + y), v'), v' = 1 / (1 / v + 1). Checked at y = 2 and, without retraining
    (``update.transport``), at y = -1: the mean within ``mean_tol`` posterior sds and the
    variance ratio inside ``var_range``."""
    mean, variance = float(particles.mean()), float(particles.var())
    for y, moved in ((2.0, posterior), (-1.0, update.transport(state, particles, jnp.array([-1.0])))):
        exact_variance = 1.0 / (1.0 / variance + 1.0)
        exact_mean = exact_variance * (mean / variance + y)
        error = (float(moved.mean()) - exact_mean) / exact_variance**0.5
        ratio = float(moved.var()) / exact_variance
        assert abs(error) < mean_tol, (y, error)
        assert var_range[0] < ratio < var_range[1], (y, ratio)
