"""What a map trained on many priors must be told about the one it is applied to.

The OT update works in the prior's standardised coordinates. For ONE prior that loses nothing,
but an amortised map serves every forecast ensemble a filter meets, and the likelihood lives in
the original coordinates: y = x^2 + noise of std 0.3 is a sharp observation of a prior of std 3
and a vague one of a prior of std 0.1, and both look alike once standardised. So the map is
given the standardisation itself (means and log-scales of the particles and of their simulated
observations) and the particles' skewness and excess kurtosis per coordinate (a negative excess
kurtosis tells a two-mode prior from a Gaussian one; the skewness, modes of unequal mass) as
extra conditioning inputs, normalised by fixed statistics of the
training ensembles (``ContextScaling``).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from ot_filter.transport.standardisation import Standardisation

Array = jax.Array

__all__ = ["ContextScaling", "context_features", "context_size", "conditioning", "fit_context_scaling"]


class ContextScaling(NamedTuple):
    mean: Array  # [c]
    scale: Array  # [c]

    def normalise(self, features: Array) -> Array:
        return (features - self.mean) / self.scale


def context_size(n: int, m: int) -> int:
    return 4 * n + 2 * m


def context_features(scaling: Standardisation, xs: Array, active: Array | None = None) -> Array:
    """``[4n + 2m]``: x mean, log x scale, y mean, log y scale, skewness and excess kurtosis of
    the standardised particles ``xs[N, n]`` (over the active rows)."""
    if active is not None:
        xs = jnp.where(active[:, None], xs, 0.0)
    count = xs.shape[0] if active is None else jnp.sum(active)
    skewness = jnp.sum(xs**3, axis=0) / count
    kurtosis = jnp.sum(xs**4, axis=0) / count - 3.0
    return jnp.concatenate([scaling.x_mean, jnp.log(scaling.x_scale), scaling.y_mean, jnp.log(scaling.y_scale),
                            skewness, kurtosis])


# Smallest scale of a feature, relative to max(1, |its mean|): a feature that hardly varies over
# the training ensembles (a log-scale in a stationary regime) must not be blown up into a large,
# noisy input by its tiny standard deviation.
MIN_RELATIVE_SCALE = 0.1


def fit_context_scaling(features: Array) -> ContextScaling:
    """Mean and standard deviation of ``features[E, c]`` over ensembles, the latter at least
    ``MIN_RELATIVE_SCALE`` max(1, |mean|)."""
    mean = jnp.mean(features, axis=0)
    floor = MIN_RELATIVE_SCALE * jnp.maximum(1.0, jnp.abs(mean))
    return ContextScaling(mean, jnp.maximum(jnp.std(features, axis=0), floor))


def conditioning(y: Array, context: Array | None) -> Array:
    """What the networks condition on: ``y[..., m]``, with the context ``[c]`` or ``[..., c]``
    appended when there is one."""
    if context is None:
        return y
    return jnp.concatenate([y, jnp.broadcast_to(context, y.shape[:-1] + context.shape[-1:])], axis=-1)
