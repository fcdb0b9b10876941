"""Built-in continuous-time models.

- ``ornstein_uhlenbeck``: linear drift, constant diffusion, linear observation, Gaussian pi_0;
  the Kalman-Bucy filter (``kalman_bucy``) is exact for it.
- ``squared_observation_sde``: dY = X (.) X dt + sigma dW with X ~ N(mu, s^2 I) static (or
  slowly diffusing). Y only sees |X|, so the posterior is bimodal (+-sqrt(.) per coordinate); the
  constant (EnKF-like) gain Cov(X, h(X)) is zero for a symmetric ensemble and cannot move the
  particles, while the exact gain of the N(0, 1) prior is K(x) = x. For a static state the
  posterior is known in closed form, p(x | Y_t) ∝ p_0(x) exp(x^2 Y_t - x^4 t / 2) per coordinate
  (sigma = 1), which ``reference.grid_posterior`` normalises.
- ``lorenz63_sde``: the Lorenz-63 vector field with additive noise and continuous observation of
  chosen components.
"""

from __future__ import annotations

from typing import NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ot_filter.continuous.sde import SDEModel
from ot_filter.lib.validation import check_int
from ot_filter.models._gaussian_observation import check_nonnegative, check_positive
from ot_filter.models.lorenz import lorenz63_vector_field

Array = jax.Array

__all__ = [
    "LinearSDEParameters",
    "lorenz63_sde",
    "ornstein_uhlenbeck",
    "squared_observation_sde",
]


class LinearSDEParameters(NamedTuple):
    """dX = A X dt + B dB, dY = H X dt + sigma dW, X_0 ~ N(m0, P0)."""

    drift_matrix: Array  # A [n, n]
    diffusion_matrix: Array  # B [n, q]
    observation_matrix: Array  # H [m, n]
    observation_noise_std: Array  # sigma [m]
    initial_mean: Array  # m0 [n]
    initial_cov: Array  # P0 [n, n]


def ornstein_uhlenbeck(
    state_dim: int = 1,
    rate: float = 1.0,
    diffusion_std: float = 1.0,
    observation_matrix=None,
    observation_noise_std: float = 0.5,
    initial_mean=None,
    initial_std: float = 1.0,
) -> SDEModel:
    """dX = -rate X dt + diffusion_std dB, dY = H X dt + sigma dW, X_0 ~ N(m0, initial_std^2 I).

    ``observation_matrix`` H defaults to the identity (every component observed).
    """
    n = check_int("state_dim", state_dim)
    rate = float(rate)
    diffusion_std = check_nonnegative("diffusion_std", diffusion_std)
    sigma = check_positive("observation_noise_std", observation_noise_std)
    initial_std = check_nonnegative("initial_std", initial_std)
    H = jnp.eye(n) if observation_matrix is None else jnp.asarray(observation_matrix, dtype=float)
    if H.ndim != 2 or H.shape[1] != n:
        raise ValueError(f"observation_matrix must have shape [m, {n}], got {H.shape}")
    m0 = jnp.zeros(n) if initial_mean is None else jnp.asarray(initial_mean, dtype=float)
    if m0.shape != (n,):
        raise ValueError(f"initial_mean must have shape ({n},), got {m0.shape}")
    A = -rate * jnp.eye(n)
    B = diffusion_std * jnp.eye(n)
    parameters = LinearSDEParameters(
        A, B, H, jnp.full((H.shape[0],), sigma), m0, initial_std**2 * jnp.eye(n)
    )

    def sample_initial(key):
        return m0 + initial_std * jax.random.normal(key, (n,))

    return SDEModel(
        drift=lambda x: A.astype(x.dtype) @ x,
        diffusion=lambda x: jnp.full_like(x, diffusion_std),
        observation_function=lambda x: H.astype(x.dtype) @ x,
        sample_initial=sample_initial,
        observation_noise_std=sigma,
        parameters=parameters,
    )


def squared_observation_sde(
    state_dim: int = 1,
    observation_noise_std: float = 1.0,
    diffusion_std: float = 0.0,
    initial_mean: float = 0.0,
    initial_std: float = 1.0,
) -> SDEModel:
    """dX = diffusion_std dB (static by default), dY = X (.) X dt + sigma dW, X_0 ~ N(mu, s^2 I)."""
    n = check_int("state_dim", state_dim)
    diffusion_std = check_nonnegative("diffusion_std", diffusion_std)
    sigma = check_positive("observation_noise_std", observation_noise_std)
    initial_std = check_positive("initial_std", initial_std)
    initial_mean = float(initial_mean)

    def sample_initial(key):
        return initial_mean + initial_std * jax.random.normal(key, (n,))

    return SDEModel(
        drift=jnp.zeros_like,
        diffusion=lambda x: jnp.full_like(x, diffusion_std),
        observation_function=lambda x: x * x,
        sample_initial=sample_initial,
        observation_noise_std=sigma,
    )


def lorenz63_sde(
    diffusion_std: float = 1.0,
    observed: Sequence[int] = (0, 1, 2),
    observation_noise_std: float = 1.0,
    initial_mean: Sequence[float] = (1.509, -1.531, 25.46),
    initial_std: float = 1.0,
    sigma: float = 10.0,
    rho: float = 28.0,
    beta: float = 8.0 / 3.0,
) -> SDEModel:
    """dX = f_L63(X) dt + diffusion_std dB, dY = X[observed] dt + observation_noise_std dW."""
    diffusion_std = check_nonnegative("diffusion_std", diffusion_std)
    noise = check_positive("observation_noise_std", observation_noise_std)
    initial_std = check_nonnegative("initial_std", initial_std)
    observed = np.asarray(observed, dtype=int)
    if observed.ndim != 1 or observed.size == 0 or observed.min() < 0 or observed.max() > 2:
        raise ValueError(f"observed must be a non-empty sequence of indices in [0, 3), got {observed!r}")
    mean = jnp.asarray(initial_mean, dtype=float)
    if mean.shape != (3,):
        raise ValueError(f"initial_mean must have shape (3,), got {mean.shape}")

    def sample_initial(key):
        return mean + initial_std * jax.random.normal(key, (3,))

    return SDEModel(
        drift=lambda x: lorenz63_vector_field(x, sigma, rho, beta),
        diffusion=lambda x: jnp.full_like(x, diffusion_std),
        observation_function=lambda x: x[observed],
        sample_initial=sample_initial,
        observation_noise_std=noise,
    )
