"""The OT update's divergence tests: when a trained map must not be used.

Divergence without NaN is the common failure of the saddle point (f's scale grows and J climbs
long before anything overflows), so the loss LEVEL is tested, not only finiteness. A step
diverged when any of these holds:

- a non-finite loss, parameters or optimiser state (``saddle.TrainingTrace.finite``);
- an exploding smoothed loss, |J| > ``threshold * n`` in standardised units (a converged J is at
  most about 2n);
- transported particles that are non-finite, or spread more than ``MAX_POSTERIOR_SPREAD`` prior
  standard deviations;
- the observation more than ``MAX_PREDICTIVE_Z`` standard deviations from the observations
  simulated at the transported particles (a tight ensemble parked in the wrong place: a loss and
  spread that look healthy).
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp

from ot_filter.lib.ensemble import masked_mean_and_std

Array = jax.Array

__all__ = ["MAX_POSTERIOR_SPREAD", "MAX_PREDICTIVE_Z", "diverged", "predictive_z"]

# Transported particles spreading more than this many prior standard deviations mean divergence.
MAX_POSTERIOR_SPREAD = 10.0
# The observation more than this many posterior-predictive standard deviations from the
# posterior-predictive mean means a misplaced ensemble (a correct posterior gives a few at most).
MAX_PREDICTIVE_Z = 10.0


def predictive_z(key: Array, sample_observation: Callable, particles: Array, observation: Array,
                 active: Array) -> Array:
    """max over coordinates of |y - mean Y'| / std Y', with Y' simulated at ``particles[N, n]``
    (non-finite particles replaced by 0 for the simulation; the active rows only; over the
    observed coordinates, NaN ones being missing)."""
    safe = jnp.where(jnp.isfinite(particles), particles, 0.0)
    predicted = jax.vmap(sample_observation)(jax.random.split(key, particles.shape[0]), safe)
    mean, std = masked_mean_and_std(predicted, active)
    z = jnp.abs(observation - mean) / (std + 1e-12)
    return jnp.max(jnp.where(jnp.isfinite(observation), z, 0.0))


def diverged(trace_finite: Array, smoothed_loss: Array, threshold, n: int, moved_standard: Array,
             active: Array, z: Array) -> Array:
    """The divergence test above (bool scalar); ``moved_standard[N, n]`` are the transported
    particles in standardised coordinates."""
    _, spread = masked_mean_and_std(moved_standard, active)
    return (
        ~trace_finite
        | ~(jnp.abs(smoothed_loss) <= threshold * n)
        | ~jnp.all(jnp.isfinite(moved_standard) | ~active[:, None])
        | ~(jnp.max(spread) <= MAX_POSTERIOR_SPREAD)
        | ~(z <= MAX_PREDICTIVE_Z)
    )
