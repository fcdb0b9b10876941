"""The interface every Bayes update implements (optax-style: a NamedTuple of pure functions).

    update = ot_filter.sir(...)                        # static configuration at build time
    state = update.init(key, particles, model)         # particles[N, n]
    particles, state, info = update.apply(key, state, particles, observation, model)

``apply`` maps prior particles (after propagation) and an observation ``y[m]`` to posterior
particles. Every state carries ``log_weights[N]``, normalised (logsumexp = 0): the posterior is
the weighted empirical measure ``sum_i exp(log_weights_i) delta_{X^i}`` (uniform except for SIR
between resampling steps). ``info`` holds per-step diagnostics; ``run_filter`` stacks them.
``init`` is given the model because some states depend on it (the OT update's networks need the
observation dimension); SIR and EnKF ignore it. An update may offer more than ``init``/``apply``
(``ot()`` returns an ``OTUpdate`` that also exposes its trained map); ``run_filter`` accepts any
NamedTuple with these two.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp

Array = jax.Array


class BayesUpdate(NamedTuple):
    """A Bayes update: ``init(key, particles, model=None) -> state`` and
    ``apply(key, state, particles, observation, model) -> (particles, state, info)``."""

    init: Callable[..., Any]  # (key, particles, model=None) -> state
    apply: Callable[..., tuple[Array, Any, Any]]


class UniformWeightsState(NamedTuple):
    """State of updates whose particles are equally weighted (EnKF)."""

    log_weights: Array  # [N], all equal to -log N


def uniform_log_weights(particles: Array) -> Array:
    num_particles = particles.shape[0]
    return jnp.full((num_particles,), -jnp.log(num_particles), dtype=particles.dtype)
