"""Saddle-point training of the conditional OT map (chapter, Sec. "Bayes update with optimal
transport", Steps 1-4; sign convention of ../shared/paper/NOTES.md).

With (X^i, Y^i) ~ P_XY and Xbar an independent copy of X, the empirical objective is

    J(f, T) = mean_i f(X^i, Y^i)
              + mean_i [ 0.5 |T(Xbar^i, Y^i) - Xbar^i|^2 - f(T(Xbar^i, Y^i), Y^i) ],

solved as max over f, min over T. Each outer iteration draws a fresh mini-batch: indices i for
the joint pairs and, independently, indices j for Xbar (the independent coupling P_X (x) P_Y),
takes ``inner_steps`` optimiser steps on T with f fixed (on that same mini-batch, as in the
authors' code), then one ascent step on f (optax
minimises, so it is given the negated gradient). The whole loop is one ``lax.fori_loop`` whose
carry is plain pytrees (network parameters and optimiser states): training can be vmapped over
seeds or simulations, warm-started from a previous result, and its trip count may be traced.

Optional EnKF layer (chapter, "EnKF layer"): T's input is x_e = xbar + K (y - ybar), where ybar is
the observation simulated from xbar and K = Cov(X, Y) Cov(Y)^{-1} is estimated from the current
mini-batch during training (from all particles at inference). The network then only learns the
non-Gaussian correction.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import optax

from ot_filter.lib.ensemble import masked_mean_and_anomalies, mean_and_anomalies
from ot_filter.lib.gaussian import cholesky_gain
from ot_filter.lib.linalg import symmetrise
from ot_filter.transport.context import conditioning

Array = jax.Array

__all__ = [
    "Batch",
    "SaddleParams",
    "TrainingState",
    "TrainingTrace",
    "batch_gain",
    "enkf_gain",
    "evaluate_saddle",
    "saddle_objective",
    "train_saddle",
]

# Relative ridge added to Cov(Y) in the EnKF layer's gain (standardised data: Cov(Y) ~ I).
GAIN_RIDGE = 1e-4
# Smoothing of the loss trace used by the divergence test (about the last 50 iterations).
LOSS_SMOOTHING = 0.98


class SaddleParams(NamedTuple):
    potential: Any  # f's flax parameters
    transport: Any  # T's flax parameters


class TrainingState(NamedTuple):
    """Everything training carries: warm-start a later training from it."""

    params: SaddleParams
    potential_opt_state: Any
    transport_opt_state: Any


class TrainingTrace(NamedTuple):
    loss: Array  # [record_length] J on each outer iteration's mini-batch (+inf: not run or not finite)
    smoothed_loss: Array  # scalar: exponential moving average of J at the end
    finite: Array  # bool scalar: every J, the final parameters and optimiser states are finite


class Batch(NamedTuple):
    x: Array  # [B, n]  X^i of the joint pairs
    y: Array  # [B, m]  Y^i of the joint pairs
    xbar: Array  # [B, n]  independent copies Xbar^j
    ybar: Array  # [B, m]  the observations simulated from Xbar^j (used by the EnKF layer only)
    gain: Array | None = None  # [B, n, m] per-pair EnKF-layer gains (the localised update);
    #                            None: the layer, if on, estimates one gain from the batch
    context: Array | None = None  # [B, c] what each pair's prior is (``transport/context.py``),
    #                               appended to y wherever a network reads it; None: nothing


def enkf_gain(x: Array, y: Array, active: Array | None = None) -> Array:
    """``K[n, m] = Cov(X, Y) (Cov(Y) + ridge I)^{-1}`` from the pairs ``x[B, n], y[B, m]``
    (only the rows where ``active[B]`` is True, if given: a padded particle axis)."""
    if active is None:
        num = x.shape[0]
        _, x_anomalies = mean_and_anomalies(x)
        _, y_anomalies = mean_and_anomalies(y)
    else:
        num_active = jnp.sum(active, dtype=jnp.int32)
        num = num_active.astype(x.dtype)
        _, x_anomalies = masked_mean_and_anomalies(x, active, num_active)
        _, y_anomalies = masked_mean_and_anomalies(y, active, num_active)
    cross = x_anomalies.T @ y_anomalies / (num - 1)
    cov_y = symmetrise(y_anomalies.T @ y_anomalies / (num - 1))
    ridge = GAIN_RIDGE * (1.0 + jnp.trace(cov_y) / cov_y.shape[0])
    gain, _ = cholesky_gain(cross, cov_y + ridge * jnp.eye(cov_y.shape[0], dtype=cov_y.dtype))
    return gain


def transport_input(xbar: Array, y: Array, ybar: Array, gain: Array | None) -> Array:
    """The EnKF layer x_e = xbar + K (y - ybar), or xbar itself without it; ``gain[n, m]`` shared
    by the rows, or ``gain[B, n, m]`` one per row."""
    if gain is None:
        return xbar
    if gain.ndim == 3:
        return xbar + jnp.einsum("bnm,bm->bn", gain, y - ybar)
    return xbar + (y - ybar) @ gain.T


def transport_cost(transport: Callable, batch: Batch, gain, cost_from_layer: bool = False):
    """``(T(x_e, y), 0.5 |T(x_e, y) - origin|^2)`` on a mini-batch, x_e the EnKF layer's output
    (or xbar). The origin is xbar (the chapter's objective), or x_e with ``cost_from_layer``: T is
    then the OT map from the layer's analysis to the posterior, a correction that is the identity
    when the layer is already right. (Measured from xbar, T cannot see the observation noise the
    layer added, and the cheapest map shrinks it away: the ensemble collapses unless f holds it.)"""
    inputs = transport_input(batch.xbar, batch.y, batch.ybar, gain)
    moved = transport(inputs, conditioning(batch.y, batch.context))
    origin = inputs if cost_from_layer else batch.xbar
    return moved, 0.5 * jnp.sum((moved - origin) ** 2, axis=-1)


def saddle_objective(potential: Callable, transport: Callable, batch: Batch, gain=None,
                     cost_from_layer: bool = False) -> Array:
    """J(f, T) on a mini-batch; ``potential(x, y) -> [B]``, ``transport(x, y) -> [B, n]``."""
    moved, cost = transport_cost(transport, batch, gain, cost_from_layer)
    y = conditioning(batch.y, batch.context)
    return jnp.mean(potential(batch.x, y)) + jnp.mean(cost - potential(moved, y))


def batch_gain(batch: Batch, enkf_layer: bool) -> Array | None:
    """The EnKF layer's gain for a mini-batch: the batch's own per-pair gains, else one estimated
    from its pairs (None without the layer)."""
    if batch.gain is None and enkf_layer:
        return enkf_gain(batch.x, batch.y)
    return batch.gain


def evaluate_saddle(key: Array, params: SaddleParams, sample_batch: Callable[[Array], Batch], *,
                    potential_net, transport_net, enkf_layer: bool, cost_from_layer: bool = False) -> Array:
    """J(f, T) of fixed parameters on one mini-batch (a validation loss: no step taken)."""
    batch = sample_batch(key)
    return saddle_objective(
        lambda x, y: potential_net.apply(params.potential, x, y),
        lambda x, y: transport_net.apply(params.transport, x, y),
        batch, batch_gain(batch, enkf_layer), cost_from_layer,
    )


def train_saddle(
    key: Array,
    state: TrainingState,
    sample_batch: Callable[[Array], Batch],
    num_iterations: Array | int,
    *,
    potential_net,
    transport_net,
    potential_optimizer: optax.GradientTransformation,
    transport_optimizer: optax.GradientTransformation,
    inner_steps: int,
    enkf_layer: bool,
    record_length: int,
    cost_from_layer: bool = False,
) -> tuple[TrainingState, TrainingTrace]:
    """Runs ``num_iterations`` outer iterations (traced allowed, at most ``record_length``).
    ``cost_from_layer``: measure the transport cost from the EnKF layer's output
    (``transport_cost``).

    ``sample_batch(key) -> Batch`` draws one mini-batch (standardised data). Returns the final
    state and the trace; J of iteration k is ``trace.loss[k]``.
    """

    def potential(params):
        return lambda x, y: potential_net.apply(params, x, y)

    def transport(params):
        return lambda x, y: transport_net.apply(params, x, y)

    def transport_loss(transport_params, potential_params, batch, gain):
        moved, cost = transport_cost(transport(transport_params), batch, gain, cost_from_layer)
        return jnp.mean(cost - potential(potential_params)(moved, conditioning(batch.y, batch.context)))

    def objective(potential_params, transport_params, batch, gain):
        return saddle_objective(potential(potential_params), transport(transport_params), batch, gain,
                                cost_from_layer)

    def outer(iteration, carry):
        state, loss, smoothed, finite = carry
        batch = sample_batch(jax.random.fold_in(key, iteration))
        gain = batch_gain(batch, enkf_layer)
        params = state.params

        def inner(_, inner_carry):
            transport_params, opt_state = inner_carry
            grads = jax.grad(transport_loss)(transport_params, params.potential, batch, gain)
            updates, opt_state = transport_optimizer.update(grads, opt_state, transport_params)
            return optax.apply_updates(transport_params, updates), opt_state

        transport_params, transport_opt_state = jax.lax.fori_loop(
            0, inner_steps, inner, (params.transport, state.transport_opt_state)
        )
        value, grads = jax.value_and_grad(objective)(params.potential, transport_params, batch, gain)
        ascent = jax.tree.map(jnp.negative, grads)  # maximise over f
        updates, potential_opt_state = potential_optimizer.update(
            ascent, state.potential_opt_state, params.potential
        )
        potential_params = optax.apply_updates(params.potential, updates)
        state = TrainingState(
            SaddleParams(potential_params, transport_params), potential_opt_state, transport_opt_state
        )
        if record_length:  # 0: nothing recorded (a budget of 0, an offline map used as is)
            loss = loss.at[iteration].set(value, mode="drop")
        smoothed = jnp.where(
            iteration == 0, value, LOSS_SMOOTHING * smoothed + (1 - LOSS_SMOOTHING) * value
        )
        return state, loss, smoothed, finite & jnp.isfinite(value)

    dtype = jax.tree.leaves(state.params)[0].dtype
    carry = (state, jnp.full((record_length,), jnp.inf, dtype), jnp.zeros((), dtype), jnp.array(True))
    state, loss, smoothed, finite = jax.lax.fori_loop(0, num_iterations, outer, carry)
    # Parameters and optimiser states (an overflowing Adam moment would poison a warm start).
    leaves = [leaf for leaf in jax.tree.leaves(state) if jnp.issubdtype(leaf.dtype, jnp.inexact)]
    state_finite = jnp.all(jnp.array([jnp.all(jnp.isfinite(leaf)) for leaf in leaves]))
    loss = jnp.where(jnp.isfinite(loss), loss, jnp.inf)
    return state, TrainingTrace(loss, smoothed, finite & state_finite)
