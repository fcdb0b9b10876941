"""Linear-Gaussian state-space model (the one case with an exact finite-dimensional filter).

    X_0 ~ N(m0, P0),   X_t = A X_{t-1} + U_t,  U_t ~ N(0, Q),   Y_t = H X_t + V_t,  V_t ~ N(0, R).

The matrices are kept in ``model.parameters`` so that ``ot_filter.kalman_filter`` can compute the
exact filtering distributions the particle filters are tested against.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from ot_filter.lib.gaussian import gaussian_log_density, restrict_to_observed
from ot_filter.lib.linalg import psd_sqrt
from ot_filter.model import StateSpaceModel, check_covariance

Array = jax.Array


class LinearGaussianParameters(NamedTuple):
    """Matrices of a linear-Gaussian model: ``A[n,n] Q[n,n] H[m,n] R[m,m] m0[n] P0[n,n]``."""

    transition_matrix: Array
    transition_cov: Array
    observation_matrix: Array
    observation_cov: Array
    initial_mean: Array
    initial_cov: Array


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
    check_covariance("Q", Q, n, positive_definite=False)
    check_covariance("R", R, m, positive_definite=True)
    check_covariance("P0", P0, n, positive_definite=False)

    parameters = LinearGaussianParameters(A, Q, H, R, m0, P0)
    transition_sqrt, observation_sqrt, initial_sqrt = psd_sqrt(Q), psd_sqrt(R), psd_sqrt(P0)

    def sample_initial(key):
        return m0 + initial_sqrt @ jax.random.normal(key, (n,), m0.dtype)

    def sample_transition(key, x):
        return A @ x + transition_sqrt @ jax.random.normal(key, (n,), x.dtype)

    def observation_function(x):
        return H @ x

    def sample_observation(key, x):
        return H @ x + observation_sqrt @ jax.random.normal(key, (m,), x.dtype)

    # The full Gaussian density, normalising constant included: SIR's marginal likelihood
    # estimate is then comparable with the Kalman filter's. NaN components of y are missing:
    # the density of the others (lib.gaussian.restrict_to_observed; R's factor then depends on
    # y only, so under vmap over particles it is computed once).
    def log_likelihood(y, x):
        observed = jnp.isfinite(y)
        chol = jnp.linalg.cholesky(restrict_to_observed(R, observed))
        return gaussian_log_density(y - H @ x, chol, observed)

    return StateSpaceModel(
        sample_initial=sample_initial,
        sample_transition=sample_transition,
        sample_observation=sample_observation,
        log_likelihood=log_likelihood,
        observation_function=observation_function,
        observation_noise_cov=R,
        parameters=parameters,
    )
