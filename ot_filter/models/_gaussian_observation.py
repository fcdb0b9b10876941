"""Additive Gaussian observation noise with diagonal covariance, shared by the built-in models."""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp

from ot_filter.model import StateSpaceModel

Array = jax.Array


def check_nonnegative(name: str, value: float) -> float:
    value = float(value)
    if not value >= 0.0:  # also rejects NaN
        raise ValueError(f"{name} must be >= 0, got {value}")
    return value


def check_positive(name: str, value: float) -> float:
    value = float(value)
    if not value > 0.0:
        raise ValueError(f"{name} must be > 0, got {value}")
    return value


def with_gaussian_observation(
    sample_initial: Callable,
    sample_transition: Callable,
    observation_function: Callable,
    observation_dim: int,
    observation_noise_std: float,
    parameters=None,
) -> StateSpaceModel:
    """Completes a model with ``Y = h(X) + std * W``, ``W ~ N(0, I_m)``: sampler, h, R, log l."""
    std = check_positive("observation_noise_std", observation_noise_std)
    log_normaliser = -observation_dim * (0.5 * jnp.log(2 * jnp.pi) + jnp.log(std))

    def sample_observation(key, x):
        hx = observation_function(x)
        return hx + std * jax.random.normal(key, hx.shape, hx.dtype)

    def log_likelihood(y, x):
        return log_normaliser - 0.5 * jnp.sum(((y - observation_function(x)) / std) ** 2)

    return StateSpaceModel(
        sample_initial=sample_initial,
        sample_transition=sample_transition,
        sample_observation=sample_observation,
        log_likelihood=log_likelihood,
        observation_function=observation_function,
        observation_noise_cov=std**2 * jnp.eye(observation_dim),
        parameters=parameters,
    )
