"""Exact one-dimensional optimal transport of an equally weighted ensemble to its reweighting.

In one dimension an optimal coupling (for any convex cost; unique up to ties) between the
uniform empirical measure of ``x[k]`` and the weighted one ``sum_l w_l delta_{x_l}`` is the
monotone one: sort both, and the particle of rank r holds the quantiles u in [r/k, (r+1)/k] of
the weighted measure.
The ensemble transform particle filter (Reich 2013) moves each particle to the barycentre of what
the coupling sends it, k times the integral of the weighted quantile function Q over its
interval:

    x_r  ->  k (G((r + 1)/k) - G(r/k)),   G(u) = int_0^u Q(s) ds,

and G is piecewise linear with knots at the cumulative weights, so each particle costs one
``searchsorted``: O(k log k), no k x k coupling. The map is monotone (ranks are kept) and keeps
the weighted mean exactly; uniform weights give the identity.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

Array = jax.Array

__all__ = ["monotone_transport"]


def monotone_transport(values: Array, log_weights: Array, active: Array | None = None) -> Array:
    """``[N]``: the barycentric projection of the optimal coupling between the equally weighted
    active entries of ``values[N]`` and the same entries weighted by ``exp(log_weights[N])``
    (unnormalised; -inf is weight 0). ``active[N]`` (default all): padding rows take no part
    and come back unchanged."""
    num = values.shape[0]
    if active is None:
        active = jnp.ones(num, bool)
    dtype = values.dtype
    count = jnp.sum(active, dtype=jnp.int32)
    log_weights = jnp.where(active, log_weights, -jnp.inf)
    weights = jnp.exp(log_weights - jax.nn.logsumexp(log_weights))
    # Centred, so that the cumulative sums G stay small and their differences keep their digits.
    centre = jnp.sum(jnp.where(active, weights * values, 0.0))
    order = jnp.argsort(jnp.where(active, values, jnp.inf))  # padding last
    rank = jnp.arange(num)
    centred = jnp.where(rank < count, values[order] - centre, 0.0)
    sorted_weights = jnp.where(rank < count, weights[order], 0.0)
    # Q's knots: sorted (an ulp over 1 would unsort them) and exactly 1 from the last active one.
    upper = jnp.where(rank >= count - 1, 1.0, jnp.minimum(jnp.cumsum(sorted_weights), 1.0))
    integral = jnp.cumsum(sorted_weights * centred)  # G at the knots

    def quantile_integral(u):  # G(u): the knot at or after u, less the linear piece beyond u
        index = jnp.clip(jnp.searchsorted(upper, u), 0, num - 1)
        return integral[index] - (upper[index] - u) * centred[index]

    size = jnp.asarray(count, dtype)
    bounds = quantile_integral(jnp.minimum(jnp.arange(num + 1, dtype=dtype) / size, 1.0))
    moved = centre + size * (bounds[1:] - bounds[:-1])
    return jnp.where(active, jnp.zeros_like(values).at[order].set(moved), values)
