"""Small, numerically careful linear-algebra helpers shared by the filters."""

from __future__ import annotations

import jax
import jax.numpy as jnp

Array = jax.Array


def symmetrise(matrix: Array) -> Array:
    """(M + M^T) / 2 over the last two axes."""
    return 0.5 * (matrix + jnp.swapaxes(matrix, -1, -2))


def psd_sqrt(matrix: Array) -> Array:
    """A square root L with L L^T = M for a symmetric positive SEMI-definite M (eigh-based).

    Unlike Cholesky it accepts singular matrices (e.g. noise acting on some components only).
    """
    eigenvalues, eigenvectors = jnp.linalg.eigh(symmetrise(matrix))
    return eigenvectors * jnp.sqrt(jnp.clip(eigenvalues, 0.0))


def truncated_pinv_solve(matrix: Array, rhs: Array, relative_cutoff: float):
    """Minimum-norm solution of ``M Z = rhs`` for symmetric PSD ``M[m, m]`` (pseudo-inverse).

    Eigen-directions with eigenvalue <= ``relative_cutoff * max eigenvalue`` are dropped
    (round-off there would otherwise be amplified by 1 / cutoff); M = 0 gives Z = 0.

    Returns ``(Z, condition)``: condition is max / min eigenvalue (inf if singular).
    """
    eigenvalues, eigenvectors = jnp.linalg.eigh(symmetrise(matrix))
    largest = jnp.max(eigenvalues)
    smallest = jnp.min(eigenvalues)
    kept = eigenvalues > jnp.maximum(relative_cutoff * largest, jnp.finfo(matrix.dtype).tiny)
    inverse_eigenvalues = jnp.where(kept, 1.0 / jnp.where(kept, eigenvalues, 1.0), 0.0)
    condition = jnp.where(smallest > 0, largest / jnp.where(smallest > 0, smallest, 1.0), jnp.inf)
    solution = eigenvectors @ (inverse_eigenvalues[:, None] * (eigenvectors.T @ rhs))
    return solution, condition
