"""Linear-Gaussian state-space model (the one case with an exact finite-dimensional filter).

    X_0 ~ N(m0, P0),   X_t = A X_{t-1} + U_t,  U_t ~ N(0, Q),   Y_t = H X_t + V_t,  V_t ~ N(0, R).

The matrices are kept in ``model.parameters`` so that ``ot_filter.kalman_filter`` can compute the
exact filtering distributions the particle filters are tested against.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ot_filter._linalg import psd_sqrt
from ot_filter.model import StateSpaceModel

Array = jax.Array


class LinearGaussianParameters(NamedTuple):
    """Matrices of a linear-Gaussian model: ``A[n,n] Q[n,n] H[m,n] R[m,m] m0[n] P0[n,n]``."""

    transition_matrix: Array
    transition_cov: Array
    observation_matrix: Array
    observation_cov: Array
    initial_mean: Array
    initial_cov: Array


def _check_covariance(name: str, matrix, size: int, positive_definite: bool) -> None:
    matrix = np.asarray(matrix, dtype=np.float64)
    if matrix.shape != (size, size):
        raise ValueError(f"{name} must have shape ({size}, {size}), got {matrix.shape}")
    if not np.all(np.isfinite(matrix)):
        raise ValueError(f"{name} must be finite")
    if not np.allclose(matrix, matrix.T, rtol=1e-6, atol=1e-10 * max(1.0, np.abs(matrix).max())):
        raise ValueError(f"{name} must be symmetric")
    smallest = np.linalg.eigvalsh(matrix).min()
    scale = max(1.0, np.abs(matrix).max())
    if positive_definite and smallest <= 0:
        raise ValueError(f"{name} must be positive definite (smallest eigenvalue {smallest:.3g})")
    if smallest < -1e-8 * scale:
        raise ValueError(f"{name} must be positive semi-definite (smallest eigenvalue {smallest:.3g})")


def linear_gaussian(A, Q, H, R, m0, P0) -> StateSpaceModel:
    """Builds the linear-Gaussian model; ``R`` must be positive definite, ``Q, P0`` PSD."""
    A, Q, H, R = (jnp.asarray(a) for a in (A, Q, H, R))
    m0, P0 = jnp.asarray(m0), jnp.asarray(P0)
    if A.ndim != 2 or A.shape[0] != A.shape[1]:
        raise ValueError(f"A must be a square matrix [n, n], got shape {A.shape}")
    n = A.shape[0]
    if H.ndim != 2 or H.shape[1] != n:
        raise ValueError(f"H must have shape [m, {n}], got {H.shape}")
    m = H.shape[0]
    if m0.shape != (n,):
        raise ValueError(f"m0 must have shape ({n},), got {m0.shape}")
    _check_covariance("Q", Q, n, positive_definite=False)
    _check_covariance("R", R, m, positive_definite=True)
    _check_covariance("P0", P0, n, positive_definite=False)

    parameters = LinearGaussianParameters(A, Q, H, R, m0, P0)
    transition_sqrt, observation_sqrt, initial_sqrt = psd_sqrt(Q), psd_sqrt(R), psd_sqrt(P0)
    observation_chol = jnp.linalg.cholesky(R)

    def sample_initial(key):
        return m0 + initial_sqrt @ jax.random.normal(key, (n,), m0.dtype)

    def sample_transition(key, x):
        return A @ x + transition_sqrt @ jax.random.normal(key, (n,), x.dtype)

    def observation_function(x):
        return H @ x

    def sample_observation(key, x):
        return H @ x + observation_sqrt @ jax.random.normal(key, (m,), x.dtype)

    # The full Gaussian density, normalising constant included: SIR's marginal likelihood
    # estimate is then comparable with the Kalman filter's.
    log_normaliser = -0.5 * m * jnp.log(2 * jnp.pi) - jnp.sum(jnp.log(jnp.diag(observation_chol)))

    def log_likelihood(y, x):
        whitened = jax.scipy.linalg.solve_triangular(observation_chol, y - H @ x, lower=True)
        return log_normaliser - 0.5 * jnp.sum(whitened**2)

    return StateSpaceModel(
        sample_initial=sample_initial,
        sample_transition=sample_transition,
        sample_observation=sample_observation,
        log_likelihood=log_likelihood,
        observation_function=observation_function,
        observation_noise_cov=R,
        parameters=parameters,
    )
