"""A-posteriori check of c-concavity (chapter, Remark after the max-min problem).

The training does not constrain f, but the chapter's error bound applies when f is
c-concave in x, i.e. phi(x, y) = 0.5 |x|^2 - f(x, y) is convex in x. We report the smallest
eigenvalue of phi's Hessian in x at the given points (>= 0: convex there).

With ReLU networks f is piecewise linear, so its exact Hessian is zero almost everywhere and the
check would always pass: the Hessian is therefore taken by central differences of the gradient
with a finite ``step`` (standardised units), which sees the kinks within ``step`` of each point
(the usual ``jax.hessian`` is recovered for smooth f as ``step -> 0``; for quadratic f the
difference quotient is exact).
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp

from ot_filter.lib.linalg import symmetrise

Array = jax.Array


def c_concavity_min_eigenvalue(
    potential: Callable[[Array, Array], Array], x: Array, y: Array, step: float = 0.1
) -> Array:
    """Smallest eigenvalue ``[P]`` of the (difference) Hessian of ``0.5|x|^2 - f(x, y)`` in x.

    Args:
      potential: ``f(x[n], y[m]) -> scalar`` for one point.
      x: ``[P, n]`` points; y: ``[P, m]`` their conditioning observations.
      step: central-difference step.
    """
    n = x.shape[-1]
    gradient = jax.grad(potential)

    def one(x_point, y_point):
        basis = step * jnp.eye(n, dtype=x_point.dtype)
        plus = jax.vmap(lambda e: gradient(x_point + e, y_point))(basis)  # [n, n]: row j = grad at +e_j
        minus = jax.vmap(lambda e: gradient(x_point - e, y_point))(basis)
        hessian_f = symmetrise((plus - minus) / (2.0 * step))
        return jnp.min(jnp.linalg.eigvalsh(jnp.eye(n, dtype=x_point.dtype) - hessian_f))

    return jax.vmap(one)(x, y)
