"""Gaussian conditioning through a Cholesky factor (Kalman filter, Kalman-Bucy, EnKF, the OT
update's EnKF layer).

For a jointly Gaussian (X, Y) with Cov(X, Y) = C ``[n, m]`` and Cov(Y) = S ``[m, m]`` (positive
definite), E[X | Y = y] = E X + K (y - E Y) with the gain K = C S^{-1}. S is factored once,
S = L L^T, and K is obtained by two triangular solves against the n columns of C^T, never by
forming S^{-1}; the same factor gives the log-density of the innovation,
log N(y - E Y; 0, S) = -m/2 log 2 pi - sum log diag L - |L^{-1} (y - E Y)|^2 / 2.

Missing components (a mask ``observed[m]``): ``restrict_to_observed`` keeps S on the observed
block and puts the identity elsewhere. With the cross-covariance's and the residual's missing
entries zero, the gain's missing columns are exactly 0 and its observed ones those of the
deleted-rows problem: the lower Cholesky factor of such a matrix has the same block structure
(no fill-in: L_ij = 0 when exactly one of i, j is missing), so the observed block's arithmetic
is that of the smaller matrix. The log-density then counts the observed dimensions only.

The optimal transport map between two Gaussians N(m, P) and N(m', Q) (quadratic cost) is affine,
x -> m' + A (x - m) with the symmetric A = P^{-1/2} (P^{1/2} Q P^{1/2})^{1/2} P^{-1/2}
(``gaussian_transport_matrix``): of every map with A P A^T = Q, the one that moves the particles
least. Applied with Q the Kalman posterior covariance it is the deterministic EnKF layer of the
OT updates (``transport/saddle.py``).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ot_filter.lib.linalg import symmetrise

Array = jax.Array

__all__ = ["cholesky_gain", "gaussian_log_density", "gaussian_transport_matrix", "restrict_to_observed"]


def cholesky_gain(cross_covariance: Array, innovation_covariance: Array) -> tuple[Array, Array]:
    """``(K[n, m], L[m, m])``: the gain ``K = C S^{-1}`` for ``C = cross_covariance[n, m]`` and a
    positive-definite ``S = innovation_covariance[m, m]``, and S's lower Cholesky factor L.

    The solves run against C's n columns (an ``[m, n]`` right-hand side), not against the data:
    O(m^2 n) whatever the number of particles."""
    chol = jnp.linalg.cholesky(innovation_covariance)
    gain = jax.scipy.linalg.cho_solve((chol, True), cross_covariance.T).T
    return gain, chol


def gaussian_transport_matrix(prior_covariance: Array, target_covariance: Array) -> Array:
    """``A[n, n]``: the linear part of the OT map from N(., P) to N(., Q) (module docstring), for
    a positive-definite P and a positive semi-definite Q (two symmetric eigendecompositions; a
    slightly indefinite Q from round-off is clipped to its PSD part)."""
    eigenvalues, vectors = jnp.linalg.eigh(symmetrise(prior_covariance))
    eigenvalues = jnp.maximum(eigenvalues, jnp.finfo(eigenvalues.dtype).tiny)
    root = (vectors * jnp.sqrt(eigenvalues)) @ vectors.T
    inverse_root = (vectors / jnp.sqrt(eigenvalues)) @ vectors.T
    middle, middle_vectors = jnp.linalg.eigh(symmetrise(root @ target_covariance @ root))
    middle_root = (middle_vectors * jnp.sqrt(jnp.clip(middle, 0.0))) @ middle_vectors.T
    return symmetrise(inverse_root @ middle_root @ inverse_root)


def restrict_to_observed(matrix: Array, observed: Array) -> Array:
    """``matrix[m, m]`` on the ``observed[m]`` block, the identity elsewhere (module docstring)."""
    identity = jnp.eye(matrix.shape[-1], dtype=matrix.dtype)
    return jnp.where(observed[:, None] & observed[None, :], matrix, identity)


def gaussian_log_density(residual: Array, chol: Array, observed: Array | None = None) -> Array:
    """``log N(residual; 0, L L^T)`` for ``residual[m]`` and a lower Cholesky factor ``L[m, m]``.

    With ``observed[m]``: the density of the observed components, for L the factor of a
    ``restrict_to_observed`` matrix (the residual's missing entries are ignored)."""
    if observed is not None:
        residual = jnp.where(observed, residual, 0.0)
    whitened = jax.scipy.linalg.solve_triangular(chol, residual, lower=True)
    dim = residual.shape[-1] if observed is None else jnp.sum(observed)
    return -0.5 * dim * jnp.log(2 * jnp.pi) - jnp.sum(jnp.log(jnp.diag(chol))) - 0.5 * whitened @ whitened
