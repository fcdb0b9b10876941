"""The Kalman-Bucy filter for linear SDE models (``continuous.models.ornstein_uhlenbeck``).

In continuous time, dm = A m dt + P H^T R^{-1} (dY - H m dt) and
dP/dt = A P + P A^T + B B^T - P H^T R^{-1} H P  (R = diag(sigma^2)). It is discretised
consistently with the data: on the grid of ``simulate_sde`` the model is the Euler-Maruyama
chain X_{k+1} = (I + A dt) X_k + B sqrt(dt) xi_k with increments dY_k = H X_k dt + sigma sqrt(dt) W_k,
and this module runs the exact Kalman filter of that chain:

    update   S = H P H^T dt + R,  K = P H^T S^{-1},  m+ = m + K (dY_k - H m dt),
             P+ = (I - K H dt) P (I - K H dt)^T + K R K^T dt          (Joseph form)
    predict  m = (I + A dt) m+,   P = (I + A dt) P+ (I + A dt)^T + B B^T dt.

It is the exact posterior of the discretised model (what SIR or the EnKF on ``discretise(model,
dt)`` converge to as N grows) and tends to the Kalman-Bucy filter at O(dt) as dt -> 0; its gain
P H^T S^{-1} is the Kalman-Bucy gain P H^T R^{-1} up to O(dt). The constant-gain FPF is a
different O(dt) discretisation of the same filter: as N grows it converges to its own mean-field
recursion (in ``tests/test_continuous.py``), which differs from this one by O(dt) (measured in
``benchmarks/fpf_linear_convergence.py``).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from ot_filter.lib.gaussian import cholesky_gain
from ot_filter.lib.linalg import symmetrise
from ot_filter.continuous.models import LinearSDEParameters
from ot_filter.continuous.sde import SDEModel, check_time_step

Array = jax.Array

__all__ = ["KalmanBucyResult", "kalman_bucy"]


class KalmanBucyResult(NamedTuple):
    mean: Array  # [T, n] E[X_{t_{k+1}} | dY_0..dY_k]
    cov: Array  # [T, n, n]


def kalman_bucy(model: SDEModel, increments: Array, dt) -> KalmanBucyResult:
    """Exact filter of the Euler-Maruyama-discretised linear model for ``increments[T, m]``."""
    parameters = getattr(model, "parameters", None)
    if not isinstance(parameters, LinearSDEParameters):
        raise TypeError(
            "kalman_bucy needs a linear model built by ot_filter.continuous.ornstein_uhlenbeck "
            "(model.parameters must be LinearSDEParameters)"
        )
    check_time_step(dt)
    m = parameters.observation_matrix.shape[0]
    if jnp.ndim(increments) != 2 or jnp.shape(increments)[1] != m:
        raise ValueError(f"increments must have shape [T, {m}], got {jnp.shape(increments)}")
    return _kalman_bucy(parameters, jnp.asarray(increments), dt)


@jax.jit
def _kalman_bucy(parameters: LinearSDEParameters, increments: Array, dt) -> KalmanBucyResult:
    A, B, H, sigma, m0, P0 = parameters
    dtype = jnp.result_type(A, increments)
    n = A.shape[0]
    transition = jnp.eye(n, dtype=dtype) + A * dt
    process_cov = B @ B.T * dt
    R = jnp.diag(sigma**2).astype(dtype)

    def step(carry, dy):
        mean, cov = carry
        S = symmetrise(H @ cov @ H.T * dt + R)
        gain, _ = cholesky_gain(cov @ H.T, S)  # P H^T S^{-1}
        mean = mean + gain @ (dy - H @ mean * dt)
        reduction = jnp.eye(n, dtype=dtype) - gain @ H * dt
        cov = symmetrise(reduction @ cov @ reduction.T + gain @ R @ gain.T * dt)
        mean = transition @ mean
        cov = symmetrise(transition @ cov @ transition.T + process_cov)
        return (mean, cov), (mean, cov)

    _, (means, covs) = jax.lax.scan(step, (m0.astype(dtype), P0.astype(dtype)), increments)
    return KalmanBucyResult(means, covs)
