"""The exact Kalman filter for ``ot_filter.models.linear_gaussian`` models.

Predict:  m- = A m,            P- = A P A^T + Q
Update:   S = H P- H^T + R,    K = P- H^T S^{-1},    m = m- + K (y - H m-),
          P = (I - K H) P- (I - K H)^T + K R K^T        (Joseph form: stays symmetric PSD)
Marginal: log p(y_t | y_{1:t-1}) = log N(y_t; H m-, S),  summed into ``log_likelihood``.

S^{-1} is applied through its Cholesky factor, never formed. NaN components of y are missing: the
update and the likelihood term are those of the model with those rows of H and R deleted (exact,
``lib.gaussian.restrict_to_observed``), and a step with nothing observed is a prediction, like
``run_filter``.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from ot_filter.lib.gaussian import cholesky_gain, gaussian_log_density, restrict_to_observed
from ot_filter.lib.linalg import symmetrise
from ot_filter.model import StateSpaceModel
from ot_filter.models.linear_gaussian import LinearGaussianParameters

Array = jax.Array

__all__ = ["KalmanResult", "kalman_filter"]


class KalmanResult(NamedTuple):
    mean: Array  # [T, n] filtering means E[X_t | y_{1:t}]
    cov: Array  # [T, n, n] filtering covariances
    log_likelihood: Array  # scalar, log p(y_{1:T})


def kalman_filter(model: StateSpaceModel, observations: Array) -> KalmanResult:
    """Exact filtering distributions of a linear-Gaussian model for ``observations[T, m]``."""
    parameters = getattr(model, "parameters", None)
    if not isinstance(parameters, LinearGaussianParameters):
        raise TypeError(
            "kalman_filter needs a model built by ot_filter.models.linear_gaussian "
            "(model.parameters must be LinearGaussianParameters)"
        )
    m = parameters.observation_matrix.shape[0]
    if jnp.ndim(observations) != 2 or jnp.shape(observations)[1] != m:
        raise ValueError(f"observations must have shape [T, {m}], got {jnp.shape(observations)}")
    return _kalman_filter(parameters, jnp.asarray(observations))


@jax.jit
def _kalman_filter(parameters: LinearGaussianParameters, observations: Array) -> KalmanResult:
    A, Q, H, R, m0, P0 = parameters
    dtype = jnp.result_type(A, observations)
    identity = jnp.eye(A.shape[0], dtype=dtype)

    def step(carry, y):
        mean, cov = carry
        mean = A @ mean
        cov = symmetrise(A @ cov @ A.T + Q)
        # NaN components are missing: zero rows of H and of the innovation, the identity in S
        # off the observed block (lib.gaussian): exactly the deleted-rows update; with nothing
        # observed the gain is 0 and the step is a prediction.
        observed = jnp.isfinite(y)
        observed_matrix = jnp.where(observed[:, None], H, 0.0)
        innovation = jnp.where(observed, y - H @ mean, 0.0)
        innovation_cov = restrict_to_observed(symmetrise(H @ cov @ H.T + R), observed)
        gain, chol = cholesky_gain(cov @ observed_matrix.T, innovation_cov)  # K = P- H^T S^{-1}
        log_likelihood = gaussian_log_density(innovation, chol, observed)
        mean = mean + gain @ innovation
        joseph = identity - gain @ observed_matrix
        cov = symmetrise(joseph @ cov @ joseph.T + gain @ R @ gain.T)
        return (mean, cov), (mean, cov, log_likelihood)

    initial = (m0.astype(dtype), P0.astype(dtype))
    _, (means, covs, log_likelihoods) = jax.lax.scan(step, initial, observations.astype(dtype))
    return KalmanResult(means, covs, jnp.sum(log_likelihoods))
