"""Resampling: draw N ancestor indices from normalised weights, unbiasedly.

Each scheme gives offspring counts with E[count_i] = N w_i (tested). They differ in variance:
multinomial (independent draws, the largest), stratified (one uniform per stratum [j/N, (j+1)/N)),
systematic (one uniform shared by all strata; counts are floor or ceil of N w_i in exact
arithmetic) and residual
(floor(N w_i) deterministic copies, the rest multinomial on the residual weights).

All take log-weights and never exponentiate them unnormalised. Stratified and systematic
resampling cost O(N): their points have one tooth per stratum [j/N, (j+1)/N), so the number of
points below each cumulative weight c_i is floor(N c_i) corrected by comparing the points of the
neighbouring strata, and the ancestors are the running count of those numbers (a histogram and a
cumulative sum; 3.8x faster than a binary search at N = 10^6 on a CPU, the same indices).
Multinomial (whose sorted uniforms come in O(N) from normalised exponential spacings) and
residual use one ``searchsorted``, O(N log N); so do the O(N) schemes when N is too large for the
stratum of a point to be resolved in the floating-point type (N >= eps^-1 / 4, about 2 * 10^6 in
float32). A point that rounding puts on a particle of zero weight (a flat stretch of the
cumulative weights, or past its end) is moved to the next particle of positive weight:
zero-weight particles are never drawn.

Padded particle axis (``updates.base``): with ``num_active = k`` (an int or a traced int scalar)
only k draws are made, from the particles of positive weight (padding has log-weight -inf, so
weight 0), and written into the first k slots: the comb has k teeth, e.g. systematic
u_j = (j + U) / k, stratified u_j = (j + U_j) / k for j < k, so each scheme is exactly the
k-particle scheme on the active weights (E[count_i] = k w_i). Slot j >= k repeats slot j mod k
(a copy of a draw: finite values to carry as padding, at log-weight -inf). Residual resampling
needs no static count: floor(k w_i) copies fill the first sum_i floor(k w_i) <= k slots, the
remaining ones are the multinomial draws, all in arrays of the static size N.
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from ot_filter.sharding import replicated
from ot_filter.lib.weights import count_dependent

Array = jax.Array

__all__ = ["RESAMPLING_SCHEMES", "resample_indices"]


def _normalised_weights(log_weights: Array) -> Array:
    return jnp.exp(log_weights - jax.nn.logsumexp(log_weights))


def _cdf(weights: Array) -> Array:
    cdf = jnp.cumsum(weights)
    # Exact 1 at the end despite rounding; and non-decreasing: XLA's parallel cumulative sum can
    # round a flat stretch (zero weights) a ulp down, where an inversion would be ill-defined.
    return jax.lax.cummax(cdf / cdf[-1])


def _invert_cdf(cdf: Array, points: Array) -> Array:
    """Index i with cdf[i-1] <= u < cdf[i] for each u in [0, 1)."""
    indices = jnp.searchsorted(cdf, points, side="right")
    return jnp.clip(indices, 0, cdf.shape[0] - 1)


def _invert_cdf_by_strata(cdf: Array, points: Array, num_active) -> Array:
    """``_invert_cdf(cdf, points)`` in O(N) for points with one tooth per stratum: slot j < k
    holds a point of [j/k, (j+1)/k) (k = ``num_active``, N if None) and slot j >= k repeats slot
    j mod k. Needs the stratum of a point to be resolved in floating point (see the module
    docstring): ``_draw`` only calls it then."""
    num = cdf.shape[0]
    count = num if num_active is None else num_active
    # q_i = #{j < k : p_j < c_i}. floor(k c_i) is the stratum of c_i up to one of rounding; the
    # points of the three strata around it are compared, those further are below / above.
    stratum = jnp.floor(count * cdf).astype(jnp.int32)

    def below(j):  # [p_j < c_i]; a slot before the first is below everything, after the last above
        inside = (j >= 0) & (j < count)
        return jnp.where(inside, points[jnp.clip(j, 0, num - 1)] < cdf, j < 0)

    below_count = stratum - 1 + below(stratum - 1) + below(stratum) + below(stratum + 1)
    below_count = jnp.clip(below_count, 0, count)
    # NaN weights (all -inf log-weights): a NaN sorts last in the binary search; same indices.
    below_count = jnp.where(jnp.isnan(cdf), count, below_count)
    # Ancestor of slot j = #{i : c_i <= p_j} = #{i : q_i <= j}: a running count of the q_i.
    histogram = jnp.zeros(num + 1, jnp.int32).at[below_count].add(1)
    indices = jnp.clip(jnp.cumsum(histogram)[:num], 0, num - 1)
    return indices if num_active is None else indices[_strata(num, num_active)]


def _draw(weights: Array, points: Array, stratified_points: bool = False, num_active=None) -> Array:
    """Inverse-CDF ancestors of ``points`` in [0, 1), never a particle of zero weight.

    ``stratified_points``: the points have one tooth per stratum (``_invert_cdf_by_strata``),
    inverted in O(N) when the dtype resolves N strata.

    Rounding in the cumulative sum can leave a point on a zero-weight particle (inside a flat
    stretch, or past the last positive weight, where padding sits): such an index moves to the
    next particle of positive weight, or to the last one. Positive-weight indices are unchanged.
    """
    num = weights.shape[0]
    cdf = _cdf(weights)
    if stratified_points and num * 4 * jnp.finfo(weights.dtype).eps < 1:
        indices = _invert_cdf_by_strata(cdf, points, num_active)
    else:
        indices = _invert_cdf(cdf, points)
    positions = jnp.arange(num)
    positive = weights > 0
    following = jax.lax.cummin(jnp.where(positive, positions, num), reverse=True)
    last = jnp.max(jnp.where(positive, positions, 0))
    nearest = jnp.where(following < num, following, last)
    nearest = jnp.where(jnp.any(positive), nearest, positions)  # NaN weights: as drawn
    return nearest[indices]


def _strata(num: int, num_active) -> Array:
    """The stratum j mod k of each of the N slots (j itself when nothing is padded)."""
    positions = jnp.arange(num)
    return positions if num_active is None else positions % num_active


def _sorted_uniforms(key: Array, num: int, dtype) -> Array:
    """num sorted iid U(0,1) in O(num): normalised partial sums of exponentials."""
    spacings = jax.random.exponential(key, (num + 1,), dtype)
    cumulative = jnp.cumsum(spacings)
    return cumulative[:-1] / cumulative[-1]


def multinomial(key: Array, log_weights: Array, num_active=None) -> Array:
    num, dtype = log_weights.shape[0], log_weights.dtype
    if num_active is None:
        points = _sorted_uniforms(key, num, dtype)
    else:
        # k sorted uniforms from the first k + 1 of N + 1 exponential spacings.
        cumulative = jnp.cumsum(jax.random.exponential(key, (num + 1,), dtype))
        points = cumulative[_strata(num, num_active)] / cumulative[num_active]
    return _draw(_normalised_weights(log_weights), points)


def stratified(key: Array, log_weights: Array, num_active=None) -> Array:
    num, dtype = log_weights.shape[0], log_weights.dtype
    offsets = jax.random.uniform(key, (num,), dtype)
    if num_active is None:
        points = (jnp.arange(num, dtype=dtype) + offsets) / num
    else:
        strata = _strata(num, num_active)
        shifted = strata.astype(dtype) + offsets[strata]
        points = count_dependent(lambda count: shifted / count, num_active, num)
    return _draw(_normalised_weights(log_weights), points, True, num_active)


def systematic(key: Array, log_weights: Array, num_active=None) -> Array:
    num, dtype = log_weights.shape[0], log_weights.dtype
    offset = jax.random.uniform(key, (), dtype)
    if num_active is None:
        points = (jnp.arange(num, dtype=dtype) + offset) / num
    else:
        shifted = _strata(num, num_active).astype(dtype) + offset
        points = count_dependent(lambda count: shifted / count, num_active, num)
    return _draw(_normalised_weights(log_weights), points, True, num_active)


def residual(key: Array, log_weights: Array, num_active=None) -> Array:
    num, dtype = log_weights.shape[0], log_weights.dtype
    count = num if num_active is None else jnp.asarray(num_active, dtype)
    scaled = count * _normalised_weights(log_weights)
    # N w_i = 0.99999994 for uniform weights in float32: a relative nudge of a few ulps keeps
    # the integer parts (and the scheme's low variance) that rounding would lose.
    eps = jnp.finfo(scaled.dtype).eps
    copies = jnp.floor(scaled * (1.0 + 8.0 * eps)).astype(jnp.int32)
    num_deterministic = jnp.sum(copies)
    # Slot j < num_deterministic goes to the particle whose copy range contains j.
    strata = _strata(num, num_active)
    deterministic = _invert_cdf(jnp.cumsum(copies), strata)
    # The remaining slots are multinomial draws from the residual weights k w - floor(k w).
    leftover = jnp.maximum(scaled - copies, 0.0)
    log_leftover = jnp.where(leftover > 0, jnp.log(jnp.where(leftover > 0, leftover, 1.0)), -jnp.inf)
    # If nothing is left over (all k w_i integers) every slot is deterministic anyway.
    log_leftover = jnp.where(
        jnp.any(leftover > 0), log_leftover, jnp.where(log_weights > -jnp.inf, 0.0, -jnp.inf)
    )
    # iid (unsorted) draws: taking the tail of a sorted sample would favour high indices.
    uniforms = jax.random.uniform(key, (num,), dtype)
    random = _draw(_normalised_weights(log_leftover), uniforms[strata])
    return jnp.where(strata < num_deterministic, deterministic, random)


RESAMPLING_SCHEMES: dict[str, Callable[..., Array]] = {
    "multinomial": multinomial,
    "stratified": stratified,
    "systematic": systematic,
    "residual": residual,
}


def resample_indices(
    key: Array, log_weights: Array, scheme: str = "systematic", num_active: Array | int | None = None
) -> Array:
    """Ancestor indices ``[N]`` drawn from ``log_weights[N]`` (any normalisation).

    ``num_active = k`` (an int or a traced int scalar, 1 <= k <= N; None means N): draw k
    ancestors into slots 0..k-1 (the comb has k teeth), slot j >= k repeats slot j mod k. The
    caller gives the padding log-weight -inf, so that it is never drawn.
    """
    if scheme not in RESAMPLING_SCHEMES:
        raise ValueError(
            f"resampling must be one of {sorted(RESAMPLING_SCHEMES)}, got {scheme!r}"
        )
    if num_active is not None and not isinstance(num_active, jax.core.Tracer):
        num = jnp.shape(log_weights)[0]
        value = np.asarray(num_active)
        if value.shape != () or not np.issubdtype(value.dtype, np.integer) or not 1 <= value <= num:
            raise ValueError(f"num_active must be an int in [1, {num}], got {num_active!r}")
    # Sharded particles: invert the cumulative weights on one replicated copy (see sharding.py).
    return RESAMPLING_SCHEMES[scheme](key, replicated(log_weights), num_active)
