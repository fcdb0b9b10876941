"""The exact Kalman filter against an independent dense joint-Gaussian computation."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ot_filter as otf
from conftest import random_linear_gaussian


def dense_filter(matrices, observations):
    """Filtering means/covariances and log p(y_{1:T}) by conditioning the joint Gaussian of
    (x_1..x_T, y_1..y_T) directly, with NumPy float64. Rows of observations with NaN are left out."""
    A, Q, H, R, m0, P0 = matrices
    n, m, T = A.shape[0], H.shape[0], observations.shape[0]
    # Z = M xi + c with xi = (x0 - m0, u_1..u_T, v_1..v_T) independent.
    num_noise = n + T * n + T * m
    M = np.zeros((T * n + T * m, num_noise))
    mean = np.zeros(T * n + T * m)
    noise_cov = np.zeros((num_noise, num_noise))
    noise_cov[:n, :n] = P0
    for t in range(T):
        noise_cov[n + t * n : n + (t + 1) * n, n + t * n : n + (t + 1) * n] = Q
        start = n + T * n + t * m
        noise_cov[start : start + m, start : start + m] = R
    x_map = np.zeros((n, num_noise))
    x_map[:, :n] = np.eye(n)
    x_mean = m0.copy()
    for t in range(T):
        x_map = A @ x_map
        x_map[:, n + t * n : n + (t + 1) * n] += np.eye(n)
        x_mean = A @ x_mean
        M[t * n : (t + 1) * n] = x_map
        mean[t * n : (t + 1) * n] = x_mean
        y_rows = slice(T * n + t * m, T * n + (t + 1) * m)
        M[y_rows] = H @ x_map
        M[y_rows, n + T * n + t * m : n + T * n + (t + 1) * m] += np.eye(m)
        mean[y_rows] = H @ x_mean
    joint_cov = M @ noise_cov @ M.T
    means, covs = [], []
    observed = np.all(np.isfinite(observations), axis=1)
    for t in range(T):
        y_index = np.concatenate(
            [np.arange(T * n + s * m, T * n + (s + 1) * m) for s in range(t + 1) if observed[s]]
            or [np.zeros(0, int)]
        )
        y_values = np.concatenate([observations[s] for s in range(t + 1) if observed[s]] or [np.zeros(0)])
        x_index = np.arange(t * n, (t + 1) * n)
        cross = joint_cov[np.ix_(x_index, y_index)]
        y_cov = joint_cov[np.ix_(y_index, y_index)]
        gain = np.linalg.solve(y_cov, cross.T).T if y_index.size else np.zeros((n, 0))
        means.append(mean[x_index] + gain @ (y_values - mean[y_index]))
        covs.append(joint_cov[np.ix_(x_index, x_index)] - gain @ cross.T)
    y_index = np.concatenate([np.arange(T * n + s * m, T * n + (s + 1) * m) for s in range(T) if observed[s]])
    residual = observations[observed].ravel() - mean[y_index]
    y_cov = joint_cov[np.ix_(y_index, y_index)]
    _, logdet = np.linalg.slogdet(2 * np.pi * y_cov)
    log_likelihood = -0.5 * (logdet + residual @ np.linalg.solve(y_cov, residual))
    return np.array(means), np.array(covs), log_likelihood


@pytest.mark.parametrize("seed", [0, 1])
def test_kalman_matches_dense_conditioning_float64(x64, seed):
    matrices = random_linear_gaussian(seed)
    model = otf.models.linear_gaussian(*matrices)
    _, observations = otf.simulate(jax.random.key(seed), model, 7)
    observations = np.asarray(observations)
    result = otf.kalman_filter(model, observations)
    assert result.mean.dtype == jnp.float64
    means, covs, log_likelihood = dense_filter(matrices, observations)
    np.testing.assert_allclose(result.mean, means, rtol=0, atol=1e-8)
    np.testing.assert_allclose(result.cov, covs, rtol=0, atol=1e-8)
    np.testing.assert_allclose(result.log_likelihood, log_likelihood, rtol=0, atol=1e-8)


def test_kalman_missing_observation_is_skipped(x64):
    matrices = random_linear_gaussian(3)
    model = otf.models.linear_gaussian(*matrices)
    _, observations = otf.simulate(jax.random.key(3), model, 6)
    observations = np.array(observations)
    observations[2] = np.nan
    result = otf.kalman_filter(model, observations)
    means, covs, log_likelihood = dense_filter(matrices, observations)
    np.testing.assert_allclose(result.mean, means, atol=1e-8)
    np.testing.assert_allclose(result.cov, covs, atol=1e-8)
    np.testing.assert_allclose(result.log_likelihood, log_likelihood, atol=1e-8)


def test_kalman_rejects_bad_input():
    with pytest.raises(TypeError, match="linear_gaussian"):
        otf.kalman_filter(otf.models.lorenz63(), np.zeros((3, 3)))
    model = otf.models.linear_gaussian(*random_linear_gaussian(0))
    with pytest.raises(ValueError, match="observations"):
        otf.kalman_filter(model, np.zeros((3, 5)))
