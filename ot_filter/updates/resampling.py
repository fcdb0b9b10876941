"""Resampling: draw N ancestor indices from normalised weights, unbiasedly.

Each scheme gives offspring counts with E[count_i] = N w_i (tested). They differ in variance:
multinomial (independent draws, the largest), stratified (one uniform per stratum [j/N, (j+1)/N)),
systematic (one uniform shared by all strata; counts are floor or ceil of N w_i in exact
arithmetic) and residual
(floor(N w_i) deterministic copies, the rest multinomial on the residual weights).

All take log-weights, never exponentiate them unnormalised, and cost O(N log N) through one
``searchsorted`` of N sorted points in the cumulative weights (multinomial gets its sorted
uniforms in O(N) from normalised exponential spacings instead of sorting).
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp

Array = jax.Array

__all__ = ["RESAMPLING_SCHEMES", "resample_indices"]


def _normalised_cdf(log_weights: Array) -> Array:
    weights = jnp.exp(log_weights - jax.nn.logsumexp(log_weights))
    cdf = jnp.cumsum(weights)
    return cdf / cdf[-1]  # exact 1 at the end despite rounding


def _invert_cdf(cdf: Array, points: Array) -> Array:
    """Index i with cdf[i-1] <= u < cdf[i] for each u in [0, 1)."""
    indices = jnp.searchsorted(cdf, points, side="right")
    return jnp.clip(indices, 0, cdf.shape[0] - 1)


def _sorted_uniforms(key: Array, num: int, dtype) -> Array:
    """num sorted iid U(0,1) in O(num): normalised partial sums of exponentials."""
    spacings = jax.random.exponential(key, (num + 1,), dtype)
    cumulative = jnp.cumsum(spacings)
    return cumulative[:-1] / cumulative[-1]


def multinomial(key: Array, log_weights: Array) -> Array:
    cdf = _normalised_cdf(log_weights)
    return _invert_cdf(cdf, _sorted_uniforms(key, log_weights.shape[0], log_weights.dtype))


def stratified(key: Array, log_weights: Array) -> Array:
    num = log_weights.shape[0]
    cdf = _normalised_cdf(log_weights)
    offsets = jax.random.uniform(key, (num,), log_weights.dtype)
    return _invert_cdf(cdf, (jnp.arange(num, dtype=log_weights.dtype) + offsets) / num)


def systematic(key: Array, log_weights: Array) -> Array:
    num = log_weights.shape[0]
    cdf = _normalised_cdf(log_weights)
    offset = jax.random.uniform(key, (), log_weights.dtype)
    return _invert_cdf(cdf, (jnp.arange(num, dtype=log_weights.dtype) + offset) / num)


def residual(key: Array, log_weights: Array) -> Array:
    num = log_weights.shape[0]
    scaled = num * jnp.exp(log_weights - jax.nn.logsumexp(log_weights))
    # N w_i = 0.99999994 for uniform weights in float32: a relative nudge of a few ulps keeps
    # the integer parts (and the scheme's low variance) that rounding would lose.
    eps = jnp.finfo(scaled.dtype).eps
    copies = jnp.floor(scaled * (1.0 + 8.0 * eps)).astype(jnp.int32)
    num_deterministic = jnp.sum(copies)
    # Slot j < num_deterministic goes to the particle whose copy range contains j.
    slots = jnp.arange(num)
    deterministic = _invert_cdf(jnp.cumsum(copies), slots)
    # The remaining slots are multinomial draws from the residual weights N w - floor(N w).
    leftover = jnp.maximum(scaled - copies, 0.0)
    log_leftover = jnp.where(leftover > 0, jnp.log(jnp.where(leftover > 0, leftover, 1.0)), -jnp.inf)
    # If nothing is left over (all N w_i integers) every slot is deterministic anyway.
    log_leftover = jnp.where(jnp.any(leftover > 0), log_leftover, jnp.zeros_like(log_leftover))
    # iid (unsorted) draws: taking the tail of a sorted sample would favour high indices.
    uniforms = jax.random.uniform(key, (num,), log_weights.dtype)
    random = _invert_cdf(_normalised_cdf(log_leftover), uniforms)
    return jnp.where(slots < num_deterministic, deterministic, random)


RESAMPLING_SCHEMES: dict[str, Callable[[Array, Array], Array]] = {
    "multinomial": multinomial,
    "stratified": stratified,
    "systematic": systematic,
    "residual": residual,
}


def resample_indices(key: Array, log_weights: Array, scheme: str = "systematic") -> Array:
    """Ancestor indices ``[N]`` drawn from ``log_weights[N]`` (any normalisation)."""
    if scheme not in RESAMPLING_SCHEMES:
        raise ValueError(
            f"resampling must be one of {sorted(RESAMPLING_SCHEMES)}, got {scheme!r}"
        )
    return RESAMPLING_SCHEMES[scheme](key, log_weights)
