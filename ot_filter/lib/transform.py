"""The ensemble transform of the ETKF (Bishop et al. 2001; Hunt et al. 2007), written once for
the global square-root EnKF and the LETKF's local analyses.

With whitened observation anomalies S ``[N, p]`` (``(h(X^i) - mean h) L^{-1} / sqrt(k - 1)``),
the whitened innovation d ``[p]`` and the state anomalies A ``[N, q]``:

    mean_a = mean + w^T A / sqrt(k - 1),   w = (I + S S^T)^{-1} S d
    A_a    = (I + S S^T)^{-1/2} A                 (the symmetric square root)

computed from the eigen-decomposition of the smaller Gram matrix: S S^T = U diag(s2) U^T
(N <= p) or S^T S = V diag(s2) V^T (p < N, with U = S V diag(s)^{-1}; the factor
(1 / sqrt(1 + s2) - 1) / s2 = -1 / (sqrt(1 + s2) (1 + sqrt(1 + s2))) is finite at s2 = 0).
Only 1 + s2 is ever inverted, so the Gram matrix's conditioning is harmless. Zero rows of S and
A (padding of a masked ensemble) and zero columns of S (unobserved or out-of-reach components)
leave the result exactly that of the smaller problem.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

Array = jax.Array

__all__ = ["etkf_transform"]


def etkf_transform(whitened: Array, innovation: Array, anomalies: Array):
    """``(w [N], A_a [N, q], s2)``: the mean weights, the posterior anomalies and the
    eigenvalues of the Gram matrix (``min(N, p)`` of them) for ``S [N, p]``, ``d [p]``,
    ``A [N, q]`` (formulas in the module docstring). ``d [p, r]``: r innovations at once (w is
    linear in d), ``w [N, r]``."""
    num, size = whitened.shape

    def per_eigenvalue(values, factors):  # scale the leading (eigen) axis of values
        return values * factors.reshape(factors.shape + (1,) * (values.ndim - 1))

    if num <= size:
        s2, left = jnp.linalg.eigh(whitened @ whitened.T)
        s2 = jnp.clip(s2, 0.0)
        mean_weights = left @ per_eigenvalue(left.T @ (whitened @ innovation), 1.0 / (1.0 + s2))
        shrink = 1.0 / jnp.sqrt(1.0 + s2) - 1.0
        return mean_weights, anomalies + left @ (shrink[:, None] * (left.T @ anomalies)), s2
    s2, right = jnp.linalg.eigh(whitened.T @ whitened)
    s2 = jnp.clip(s2, 0.0)
    mean_weights = whitened @ (right @ per_eigenvalue(right.T @ innovation, 1.0 / (1.0 + s2)))
    root = jnp.sqrt(1.0 + s2)
    shrink_over_s2 = -1.0 / (root * (1.0 + root))
    projected = right.T @ (whitened.T @ anomalies)  # [p, q]
    return mean_weights, anomalies + whitened @ (right @ (shrink_over_s2[:, None] * projected)), s2
