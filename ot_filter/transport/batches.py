"""Mini-batches of the OT update's saddle-point training (``saddle.Batch``).

Each batch draws B joint pairs (X^i, Y^i) and, independently, B copies Xbar^j (the independent
coupling), by index among the k active particles. With smoothing the states are jittered
(``standardisation.smoothed_draw``); with fresh observations the Y are simulated afresh at the
(jittered) states, so that neither network can memorise the N pairs.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp

from ot_filter.transport.saddle import Batch
from ot_filter.transport.standardisation import Standardisation, smoothed_draw

Array = jax.Array

__all__ = ["TrainingData", "own_pairs", "sample_batch", "simulate_standardised"]


class TrainingData(NamedTuple):
    """What every mini-batch is drawn from (standardised coordinates)."""

    xs: Array  # [N, n] particles
    ys: Array  # [N, m] their simulated observations
    active_index: Array  # [N] indices of the active particles first (stable order)
    num_active: Array  # int scalar
    bandwidth: Array  # smoothing bandwidth h (unused without smoothing)
    correlation_factor: Array | None  # L of the particles' correlation (None: no smoothing)
    scaling: Standardisation


def simulate_standardised(key: Array, sample_observation: Callable, scaling: Standardisation,
                          x_standard: Array) -> Array:
    """Observations simulated at standardised states ``[B, n]``, standardised ``[B, m]``."""
    x = scaling.restore_x(x_standard)
    y = jax.vmap(sample_observation)(jax.random.split(key, x.shape[0]), x)
    return scaling.standardise_y(y)


def sample_batch(key: Array, data: TrainingData, sample_observation: Callable, *, batch_size: int,
                 smoothing: bool, fresh_observations: bool, enkf_layer: bool) -> Batch:
    """One mini-batch of ``batch_size`` pairs and copies."""
    pair_key, copy_key, jitter_key, copy_jitter_key, y_key, ybar_key = jax.random.split(key, 6)
    pairs = data.active_index[jax.random.randint(pair_key, (batch_size,), 0, data.num_active)]
    copies = data.active_index[jax.random.randint(copy_key, (batch_size,), 0, data.num_active)]
    x, xbar = data.xs[pairs], data.xs[copies]
    if smoothing:
        x = smoothed_draw(jitter_key, x, data.bandwidth, data.correlation_factor)
        xbar = smoothed_draw(copy_jitter_key, xbar, data.bandwidth, data.correlation_factor)
    if fresh_observations:
        y = simulate_standardised(y_key, sample_observation, data.scaling, x)
        if enkf_layer:
            ybar = simulate_standardised(ybar_key, sample_observation, data.scaling, xbar)
        else:
            ybar = data.ys[copies]
    else:
        y, ybar = data.ys[pairs], data.ys[copies]
    return Batch(x, y, xbar, ybar)


def own_pairs(data: TrainingData, batch_size: int) -> Batch:
    """The first ``batch_size`` active pairs with their own simulated observations, and as
    copies the same pairs shifted by one (particles are exchangeable, so Xbar^i = X^(i+1) is
    independent of the pair i): a mini-batch that draws nothing, for the J of a fixed map (a
    check, not training; rows repeat when fewer particles are active)."""
    count = jnp.maximum(jnp.minimum(batch_size, data.num_active), 1)
    rows = jnp.arange(batch_size)
    pairs, copies = data.active_index[rows % count], data.active_index[(rows + 1) % count]
    return Batch(data.xs[pairs], data.ys[pairs], data.xs[copies], data.ys[copies])
