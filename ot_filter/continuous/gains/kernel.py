"""The kernel (diffusion-map) gain of Taghvaei & Mehta for the feedback particle filter.

With the Gaussian kernel g_ij = exp(-|X^i - X^j|^2 / (4 eps)), its density-normalised version
k_ij = g_ij / sqrt(d_i d_j) (d_i = sum_l g_il) and the Markov matrix T_ij = k_ij / sum_l k_il,
the Poisson equation's solution at the particles is the fixed point

    Phi = T Phi + eps (h - h_hat),     h_hat = sum_i pi_i h_i   (pi: T's stationary weights)

solved as the equivalent symmetric system (D - k) Phi = eps D (h - h_hat) by conjugate gradients
(one ``lax.while_loop`` until the relative residual is below ``tolerance``, warm-started from the
previous time step's Phi), then mean-centred. With r = Phi + eps h, the gain is the gradient of the smoothed T r:

    K(x) = (1 / (2 eps)) sum_j T(x, X^j) (X^j - sum_l T(x, X^l) X^l) (r_j - sum_l T(x, X^l) r_l)^T

(Taghvaei, de Wiljes, Mehta, Reich 2018, Alg. 2; ``../shared/paper/NOTES.md`` writes Phi where the
algorithm has r = Phi + eps h: T r = Phi + eps h_hat, so grad(T r) approximates grad phi, while
grad(T Phi) misses eps grad h, an O(eps) bias). The same formula at any x, with T(x, .) built from
the particles' d_j, extends the gain off the particles; its derivative gives the Stratonovich
correction.

Cost and memory: O(N^2 (n + m)) per sweep and about ``4 N^2`` floats of memory (g, k, T and a
temporary), 1.6 GB at N = 10^4 in float32; ``memory_limit_bytes`` bounds it (a ValueError before
any work names N and the limit). The correction is evaluated in blocks of ``block_size`` points.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from ot_filter.continuous.gains.base import (
    Gain,
    GainOutput,
    constant_gain_output,
    gain_and_correction,
)
from ot_filter.lib.fallback import use_where
from ot_filter.lib.static import bind
from ot_filter.lib.validation import check_int, check_number, is_traced

Array = jax.Array

__all__ = ["KernelGainInfo", "KernelGainSettings", "KernelGainState", "kernel_gain"]


class KernelGainSettings(NamedTuple):
    """The kernel gain's numbers (traced: ``vmap`` over them runs in one program)."""

    epsilon: Array
    tolerance: Array
    damping: Array


class KernelGainState(NamedTuple):
    potential: Array  # [N, m] the last fixed point Phi (warm start)


class KernelGainInfo(NamedTuple):
    iterations: Array  # conjugate-gradient iterations used
    residual: Array  # relative residual of the linear system
    converged: Array  # bool, residual <= 10 tolerance
    fallback: Array  # bool, the constant gain was used (no convergence, or a non-finite gain)


MATRICES_IN_MEMORY = 4  # g, k and up to two temporaries of shape [N, N]


def kernel_gain(
    epsilon: float = 0.1,
    tolerance: float = 1e-4,
    max_iterations: int = 500,
    memory_limit_bytes: float = 4 * 2**30,
    block_size: int = 512,
    damping: float = 0.01,
) -> Gain:
    """Builds the diffusion-map gain (``epsilon``, ``tolerance`` and ``damping`` may be traced;
    ``max_iterations``, ``memory_limit_bytes`` and ``block_size`` are structure).

    Args:
      epsilon: kernel bandwidth eps > 0, in squared state units (the bias is O(eps), the variance
        grows as eps shrinks).
      tolerance: stop when the relative residual of the linear system is below this (> 0).
      max_iterations: at most this many CG iterations; a step whose residual is still above 10x
        the tolerance then uses the constant gain (``info.fallback``).
      memory_limit_bytes: refuse ensembles whose N x N matrices would exceed this.
      block_size: particles per block in the Stratonovich correction.
      damping: solve ((1 + damping eps) D - k) Phi = eps D (h - h_hat), i.e. the Poisson equation
        (-L + damping) phi = h - h_hat with a small shift (a discount, in Markov-chain terms). A
        particle the kernel barely connects to the rest (a tail particle across an empty gap) is
        an almost closed component of the graph, on which the unshifted equation has no bounded
        solution: Phi there and the gain of its neighbours blow up and throw particles far off
        (measured: non-finite runs at N = 200, eps = 0.1 on dY = X^2 dt + dW). The shift bounds
        Phi by |h - h_hat| / damping at a gain shrinkage of damping / lambda for an
        eigenfunction of -L with eigenvalue lambda (1 % for the Gaussian, h = x case at the
        default; 0: none).
    """
    settings = KernelGainSettings(
        epsilon=check_number("epsilon", epsilon, 0.0, strict_minimum=True),
        tolerance=check_number("tolerance", tolerance, 0.0, strict_minimum=True),
        damping=check_number("damping", damping, 0.0),
    )
    memory_limit_bytes = check_number("memory_limit_bytes", memory_limit_bytes, 0.0, strict_minimum=True,
                                      finite=False)
    if is_traced(memory_limit_bytes):
        raise TypeError("memory_limit_bytes is structure (checked at build time): give a number, not a traced value")
    structure = dict(
        max_iterations=check_int("max_iterations", max_iterations),
        block_size=check_int("block_size", block_size),
        memory_limit_bytes=float(memory_limit_bytes),
    )
    return Gain(bind(_kernel_init, **structure), bind(_kernel_apply, settings, **structure))


def _check_memory(particles, memory_limit_bytes):
    num = particles.shape[0]
    needed = MATRICES_IN_MEMORY * num * num * particles.dtype.itemsize
    if needed > memory_limit_bytes:
        raise ValueError(
            f"kernel_gain with N = {num} particles needs about {needed / 2**30:.1f} GiB for its "
            f"N x N matrices, over memory_limit_bytes = {memory_limit_bytes / 2**30:.1f} GiB; "
            f"use fewer particles, the constant or learned gain, or raise the limit"
        )


def _kernel_init(key, particles, h_values, *, max_iterations, block_size, memory_limit_bytes):
    del key
    _check_memory(particles, memory_limit_bytes)
    return KernelGainState(jnp.zeros_like(h_values))


def _kernel_apply(settings, key, state, particles, h_values, *, max_iterations, block_size,
                  memory_limit_bytes):
    del key
    _check_memory(particles, memory_limit_bytes)
    epsilon, tolerance, damping = settings
    squared = jnp.sum(particles**2, axis=1)
    distances = jnp.maximum(squared[:, None] + squared[None, :] - 2 * particles @ particles.T, 0.0)
    g = jnp.exp(-distances / (4 * epsilon))
    degree = jnp.sum(g, axis=1)  # >= 1: g_ii = 1
    k = g / jnp.sqrt(degree[:, None] * degree[None, :])
    row_sums = jnp.sum(k, axis=1)
    # Phi = T Phi + eps (h - h_hat) is the linear system (D - k) Phi = eps D (h - h_hat) with
    # the symmetric graph Laplacian D - k (D = diag of the row sums): solvable when h_hat is
    # the mean under T's stationary weights pi ∝ D, and solved by conjugate gradients. Plain
    # fixed-point sweeps contract at 1 - O(eps) and stall on particles the kernel barely
    # connects (outliers, the trough between two modes); CG resolves such isolated
    # eigenvalues in a few iterations.
    stationary = row_sums / jnp.sum(row_sums)
    centred_h = h_values - stationary @ h_values
    forcing = epsilon * centred_h
    potential, residual, iterations = _conjugate_gradients(
        lambda v: (1.0 + damping * epsilon) * row_sums[:, None] * v - k @ v,
        row_sums[:, None] * forcing,
        state.potential,
        tolerance,
        max_iterations,
    )
    potential = potential - jnp.mean(potential, axis=0)
    r = potential + forcing

    def field(x):
        gx = jnp.exp(-jnp.sum((particles - x) ** 2, axis=1) / (4 * epsilon))
        kx = gx / jnp.sqrt(jnp.sum(gx) * degree)
        tx = kx / jnp.sum(kx)
        return ((tx[:, None] * (particles - tx @ particles)).T @ (r - tx @ r)) / (2 * epsilon)

    # At the particles too the gain is this centred local covariance (the uncentred form
    # T(X r) - (T X)(T r) loses digits to cancellation), evaluated with its derivative.
    gain, correction = jax.lax.map(
        lambda x: gain_and_correction(field, x), particles, batch_size=block_size
    )
    finite = jnp.all(jnp.isfinite(gain)) & jnp.all(jnp.isfinite(correction))
    converged = residual <= 10 * tolerance  # CG stops at tolerance; allow float rounding
    # A fixed point that does not converge has (near-)disconnected clusters of particles, whose
    # Phi grows without bound and whose gain throws particles far off: use the constant gain
    # for this step and restart the fixed point from zero.
    usable = finite & converged
    output = use_where(usable, GainOutput(gain, correction), constant_gain_output(particles, h_values))
    potential = jnp.where(usable, potential, 0.0)
    info = KernelGainInfo(iterations, residual, converged, ~usable)
    return output, KernelGainState(potential), info


def _conjugate_gradients(matvec, rhs, initial, tolerance, max_iterations):
    """CG for the symmetric positive semi-definite ``matvec`` on each column of ``rhs[N, m]``
    jointly (one while loop, a step length per column); stops when every column's relative
    residual |b - A x| / |b| is below ``tolerance``. Returns (x, worst residual, iterations)."""
    rhs_norm = jnp.maximum(jnp.linalg.norm(rhs, axis=0), 1e-30)
    residual = rhs - matvec(initial)
    tiny = jnp.finfo(rhs.dtype).tiny

    def relative(residual):
        return jnp.max(jnp.linalg.norm(residual, axis=0) / rhs_norm)

    def body(carry):
        x, residual, direction, rho, iteration = carry
        product = matvec(direction)
        alpha = rho / jnp.maximum(jnp.sum(direction * product, axis=0), tiny)
        x = x + alpha * direction
        residual = residual - alpha * product
        rho_new = jnp.sum(residual * residual, axis=0)
        direction = residual + (rho_new / jnp.maximum(rho, tiny)) * direction
        return x, residual, direction, rho_new, iteration + 1

    def cond(carry):
        _, residual, _, _, iteration = carry
        return (iteration < max_iterations) & (relative(residual) > tolerance)

    rho = jnp.sum(residual * residual, axis=0)
    x, residual, _, _, iterations = jax.lax.while_loop(
        cond, body, (initial, residual, residual, rho, 0)
    )
    return x, relative(residual), iterations
