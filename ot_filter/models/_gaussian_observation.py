"""Additive Gaussian observation noise with diagonal covariance, shared by the built-in models."""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp

from ot_filter.lib.static import bind
from ot_filter.lib.validation import check_number
from ot_filter.model import StateSpaceModel

Array = jax.Array


def check_nonnegative(name: str, value):
    """A number >= 0 (a traced one passes unchecked: ``lib.validation.check_number``)."""
    return check_number(name, value, minimum=0.0)


def check_positive(name: str, value):
    """A number > 0 (a traced one passes unchecked)."""
    return check_number(name, value, minimum=0.0, strict_minimum=True)


def gaussian_sample_observation(numbers, key, x):
    """``h(x) + std * W``; ``numbers = (std, h)``."""
    std, observation_function = numbers
    hx = observation_function(x)
    return hx + std * jax.random.normal(key, hx.shape, hx.dtype)


def gaussian_log_likelihood(numbers, y, x):
    """``log N(y_o; h(x)_o, std^2 I)`` over the observed (finite) components o of y: a NaN
    component is missing and the density is the marginal of the others (exact, the noise being
    independent per component); ``numbers = (std, h)``."""
    std, observation_function = numbers
    observed = jnp.isfinite(y)
    residual = jnp.where(observed, y - observation_function(x), 0.0) / std
    log_normaliser = -jnp.sum(observed) * (0.5 * jnp.log(2 * jnp.pi) + jnp.log(std))
    return log_normaliser - 0.5 * jnp.sum(residual**2)


def with_gaussian_observation(
    sample_initial: Callable,
    sample_transition: Callable,
    observation_function: Callable,
    observation_dim: int,
    observation_noise_std: float,
    parameters=None,
    geometry=None,
) -> StateSpaceModel:
    """Completes a model with ``Y = h(X) + std * W``, ``W ~ N(0, I_m)``: sampler, h, R, log l.

    With ``observation_function`` a ``lib.static.bind`` pytree (the built-in models), the
    sampler and log-likelihood are too: the model's numbers are traced leaves and two models
    built alike are equal as static structure (no recompilation)."""
    std = check_positive("observation_noise_std", observation_noise_std)
    as_tree = observation_function
    if not isinstance(as_tree, jax.tree_util.Partial):
        as_tree = jax.tree_util.Partial(observation_function)  # a plain function: static, by identity
    numbers = (std, as_tree)
    return StateSpaceModel(
        sample_initial=sample_initial,
        sample_transition=sample_transition,
        sample_observation=bind(gaussian_sample_observation, numbers),
        log_likelihood=bind(gaussian_log_likelihood, numbers),
        observation_function=observation_function,
        # The diagonal of R (independent noise): no m x m matrix, whatever m.
        observation_noise_cov=std**2 * jnp.ones(observation_dim),
        parameters=parameters,
        geometry=geometry,
    )
