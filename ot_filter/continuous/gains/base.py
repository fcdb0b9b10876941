"""The gain contract of the feedback particle filter, and a gain from a known function.

The FPF moves each particle by ``K(X^i) o (dY - (h(X^i) + h_hat) / 2 dt)`` (Stratonovich), where
the gain K = grad phi [n, m] solves the Poisson equation -(1/p) div(p grad phi_k) = h_k - h_hat_k
for the current particle density p. A gain approximation is a ``Gain(init, apply)`` of pure
functions of the particles and the values of the (whitened) observation function at them:

    state = init(key, particles[N, n], h_values[N, m])
    output, state, info = apply(key, state, particles[N, n], h_values[N, m])

``output.gain[N, n, m]`` is K(X^i); ``output.correction[N, n]`` is the Ito-Stratonovich
correction 0.5 sum_k (D K_k) K_k at X^i (the derivative of the gain FUNCTION at a fixed time,
computed by automatic differentiation of the gain's field), which turns the Stratonovich SDE into
the Ito one an Euler-Maruyama step integrates. ``state`` carries warm starts across time steps
(the previous fixed point, or network weights); ``info`` is a NamedTuple of per-step diagnostics.

Like the Bayes updates, the built-in gains bind module-level functions (``lib.static.bind``): a
gain is a pytree whose leaves are its numbers (epsilon, damping, tolerances, learning rate), so
``run_fpf`` takes it as a traced argument and ``vmap`` over those numbers runs in one program.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp

from ot_filter.lib.ensemble import mean_and_anomalies
from ot_filter.lib.static import bind

Array = jax.Array

__all__ = ["Gain", "GainOutput", "ConstantGainInfo", "constant_gain", "constant_gain_matrix",
           "constant_gain_output", "function_gain", "gain_and_correction", "stratonovich_correction"]


class GainOutput(NamedTuple):
    gain: Array  # [N, n, m] K(X^i)
    correction: Array  # [N, n] 0.5 sum_k (D K_k) K_k at X^i


class Gain(NamedTuple):
    init: Callable[[Array, Array, Array], Any]
    apply: Callable[[Array, Any, Array, Array], tuple[GainOutput, Any, Any]]


class ConstantGainInfo(NamedTuple):
    gain_norm: Array  # Frobenius norm of the gain (mean over particles for a varying gain)


def gain_and_correction(field: Callable[[Array], Array], x: Array) -> tuple[Array, Array]:
    """``(K(x)[n, m], 0.5 sum_k (D K_k)(x) K_k(x) [n])`` for a gain field ``x[n] -> K(x)[n, m]``
    (one point): the field is evaluated once and differentiated along its own columns."""
    value = field(x)

    def directional_derivative(direction):
        return jax.jvp(field, (x,), (direction,))[1]  # (D K)(x) . direction, [n, m]

    derivatives = jax.vmap(directional_derivative)(value.T)  # [m, n, m]: k-th direction K_k
    return value, 0.5 * jnp.einsum("knk->n", derivatives)


def stratonovich_correction(field: Callable[[Array], Array], x: Array) -> Array:
    """``0.5 sum_k (D K_k)(x) K_k(x)`` for a gain field ``x[n] -> K(x)[n, m]`` (one point)."""
    return gain_and_correction(field, x)[1]


def constant_gain_matrix(particles: Array, h_values: Array) -> Array:
    """``K[n, m] = (1/N) sum_i (X^i - x_bar)(h(X^i) - h_hat)^T``: the constant (EnKF-like) gain."""
    _, particle_anomalies = mean_and_anomalies(particles)
    _, h_anomalies = mean_and_anomalies(h_values)
    return particle_anomalies.T @ h_anomalies / particles.shape[0]


def constant_gain_output(particles: Array, h_values: Array) -> GainOutput:
    """The constant gain at every particle, with its zero correction (also the fallback of the
    kernel and learned gains when theirs is unusable)."""
    gain = constant_gain_matrix(particles, h_values)
    return GainOutput(jnp.broadcast_to(gain, (particles.shape[0], *gain.shape)), jnp.zeros_like(particles))


def _no_state(key, particles, h_values):
    del key, particles, h_values
    return ()


def _constant_apply(key, state, particles, h_values):
    del key
    output = constant_gain_output(particles, h_values)
    return output, state, ConstantGainInfo(jnp.linalg.norm(output.gain[0]))


def _function_apply(key, state, particles, h_values, *, field):
    del key, h_values
    gain, correction = jax.vmap(lambda x: gain_and_correction(field, x))(particles)
    norm = jnp.mean(jnp.sqrt(jnp.sum(gain**2, axis=(1, 2))))
    return GainOutput(gain, correction), state, ConstantGainInfo(norm)


def constant_gain() -> Gain:
    """The constant-gain (EnKF-like) approximation K = (1/N) sum_i (X^i - x_bar)(h(X^i) - h_hat)^T,
    the same for all particles: the best gain among gradients of linear functions phi, exact
    for a Gaussian density and linear h. Its correction is zero."""
    return Gain(bind(_no_state), bind(_constant_apply))


def function_gain(field: Callable[[Array], Array]) -> Gain:
    """A gain given as a function ``x[n] -> K(x)[n, m]`` (e.g. a known exact gain); the
    correction comes from differentiating it. For tests and for models with a known gain.
    (The function is static: compared by identity.)"""
    return Gain(bind(_no_state), bind(_function_apply, field=field))
