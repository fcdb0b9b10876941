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

Deterministic layer (``DeterministicLayer``, ``deterministic_layer``): x_e = m + K (y - ybar_mean)
+ A (xbar - m), A the Gaussian OT map from the prior's covariance P to the Kalman posterior's
P - K Cov(Y, X) (``lib.gaussian.gaussian_transport_matrix``). For xbar independent of y it has
the prior's moments, and at a fixed y the posterior's, exactly, without the sampling noise of
the observation perturbation ybar - E Y (the square-root EnKF's advantage over the perturbed one).
Its moments come from all particles, never from a mini-batch.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import optax

from ot_filter.lib.ensemble import masked_mean_and_anomalies, mean_and_anomalies
from ot_filter.lib.gaussian import cholesky_gain, gaussian_transport_matrix
from ot_filter.lib.linalg import symmetrise
from ot_filter.transport.context import conditioning

Array = jax.Array

__all__ = [
    "Batch",
    "DeterministicLayer",
    "SaddleParams",
    "TrainingState",
    "TrainingTrace",
    "batch_gain",
    "deterministic_layer",
    "empty_layer",
    "enkf_gain",
    "fit_layer",
    "evaluate_saddle",
    "known_noise_gain",
    "recorded_loop",
    "saddle_objective",
    "saddle_terms",
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


class DeterministicLayer(NamedTuple):
    """x_e = xbar + K (y - y_mean) + (A - I)(xbar - x_mean) (module docstring); leaves may carry
    leading axes (one layer per row of a batch, or per coordinate of the localised update)."""

    gain: Array  # [..., n, m] K
    shrink: Array  # [..., n, n] A - I
    x_mean: Array  # [..., n]
    y_mean: Array  # [..., m]


def _moments(x: Array, y: Array, active: Array | None):
    """Means, Cov(X), Cov(X, Y) and Cov(Y) of the pairs ``x[B, n], y[B, m]`` (the ``active`` rows)."""
    if active is None:
        num = x.shape[0]
        x_mean, x_anomalies = mean_and_anomalies(x)
        y_mean, y_anomalies = mean_and_anomalies(y)
    else:
        num_active = jnp.sum(active, dtype=jnp.int32)
        num = num_active.astype(x.dtype)
        x_mean, x_anomalies = masked_mean_and_anomalies(x, active, num_active)
        y_mean, y_anomalies = masked_mean_and_anomalies(y, active, num_active)
    cov_x = symmetrise(x_anomalies.T @ x_anomalies / (num - 1))
    cross = x_anomalies.T @ y_anomalies / (num - 1)
    cov_y = symmetrise(y_anomalies.T @ y_anomalies / (num - 1))
    return x_mean, y_mean, cov_x, cross, cov_y


def _ridged(cov: Array) -> Array:
    """``cov + ridge I`` with the relative ridge ``GAIN_RIDGE`` (padding coordinates stay regular)."""
    ridge = GAIN_RIDGE * (1.0 + jnp.trace(cov) / cov.shape[0])
    return cov + ridge * jnp.eye(cov.shape[0], dtype=cov.dtype)


def enkf_gain(x: Array, y: Array, active: Array | None = None) -> Array:
    """``K[n, m] = Cov(X, Y) (Cov(Y) + ridge I)^{-1}`` from the pairs ``x[B, n], y[B, m]``
    (only the rows where ``active[B]`` is True, if given: a padded particle axis)."""
    _, _, _, cross, cov_y = _moments(x, y, active)
    gain, _ = cholesky_gain(cross, _ridged(cov_y))
    return gain


def known_noise_gain(x: Array, predicted: Array, noise_cov: Array, active: Array | None = None) -> Array:
    """``K[n, m] = Cov(X, h(X)) (Cov(h(X)) + R)^{-1}``, the EnKF's gain when the observation
    noise's covariance ``R[m, m]`` is known, from ``x[B, n]`` and the noise-free predictions
    ``predicted[B, m]`` (the ``active`` rows), all in one set of coordinates. Cov(h) + R is
    positive definite: no ridge, and well conditioned where the sample Cov(Y) is not (N near m).
    Where its Cholesky factor still fails (float32, fewer particles than m and an R tiny next
    to the spread of h), the gain with ``enkf_gain``'s relative ridge is used instead."""
    _, _, _, cross, cov_h = _moments(x, predicted, active)
    innovation = cov_h + noise_cov
    gain, _ = cholesky_gain(cross, innovation)
    ridged, _ = cholesky_gain(cross, _ridged(innovation))
    return jnp.where(jnp.all(jnp.isfinite(gain)), gain, ridged)


def deterministic_layer(x: Array, y: Array, active: Array | None = None) -> DeterministicLayer:
    """The deterministic layer's K, A - I and means from the pairs ``x[B, n], y[B, m]`` (the
    ``active`` rows): A maps Cov(X) to Cov(X) - K Cov(Y, X), both with the relative ridge."""
    x_mean, y_mean, cov_x, cross, cov_y = _moments(x, y, active)
    gain, _ = cholesky_gain(cross, _ridged(cov_y))
    prior = _ridged(cov_x)
    transform = gaussian_transport_matrix(prior, symmetrise(prior - gain @ cross.T))
    return DeterministicLayer(gain, transform - jnp.eye(x.shape[1], dtype=x.dtype), x_mean, y_mean)


def fit_layer(x: Array, y: Array, active: Array | None = None, deterministic: bool = False):
    """The layer of the pairs ``x[B, n], y[B, m]``: a ``DeterministicLayer``, else the EnKF gain."""
    return deterministic_layer(x, y, active) if deterministic else enkf_gain(x, y, active)


def empty_layer(n: int, m: int, dtype, deterministic: bool = False):
    """Zeros shaped like ``fit_layer``'s result (a state's layer before the first update)."""
    if deterministic:
        return DeterministicLayer(jnp.zeros((n, m), dtype), jnp.zeros((n, n), dtype),
                                  jnp.zeros((n,), dtype), jnp.zeros((m,), dtype))
    return jnp.zeros((n, m), dtype)


def _rows(matrix: Array, vectors: Array) -> Array:
    """``matrix @ vector`` for each row of ``vectors[B, k]``: ``matrix[j, k]`` shared, or
    ``matrix[B, j, k]`` one per row."""
    if matrix.ndim == 3:
        return jnp.einsum("bjk,bk->bj", matrix, vectors)
    return vectors @ matrix.T


def transport_input(xbar: Array, y: Array, ybar: Array, gain) -> Array:
    """The layer's output x_e: the EnKF layer xbar + K (y - ybar) for ``gain`` K (``[n, m]``
    shared by the rows, or ``[B, n, m]`` one per row), the deterministic layer for a
    ``DeterministicLayer`` (which does not read ybar), xbar itself for None."""
    if gain is None:
        return xbar
    if isinstance(gain, DeterministicLayer):
        return xbar + _rows(gain.gain, y - gain.y_mean) + _rows(gain.shrink, xbar - gain.x_mean)
    return xbar + _rows(gain, y - ybar)


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


def saddle_terms(potential: Callable, transport: Callable, batch: Batch, gain=None,
                 cost_from_layer: bool = False) -> tuple[Array, Array]:
    """J's two terms per row of a mini-batch: ``(f(x, y), c(xbar, T) - f(T(xbar, y), y))``,
    each ``[B]``; ``potential(x, y) -> [B]``, ``transport(x, y) -> [B, n]``."""
    moved, cost = transport_cost(transport, batch, gain, cost_from_layer)
    y = conditioning(batch.y, batch.context)
    return potential(batch.x, y), cost - potential(moved, y)


def saddle_objective(potential: Callable, transport: Callable, batch: Batch, gain=None,
                     cost_from_layer: bool = False) -> Array:
    """J(f, T) on a mini-batch (the means of ``saddle_terms``)."""
    joint, independent = saddle_terms(potential, transport, batch, gain, cost_from_layer)
    return jnp.mean(joint) + jnp.mean(independent)


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

    def outer(iteration, state):
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
        return state, value

    return recorded_loop(outer, state, num_iterations, record_length)


def recorded_loop(step: Callable, state, num_iterations: Array | int, record_length: int):
    """Runs ``step(iteration, state) -> (state, value)`` ``num_iterations`` times (traced
    allowed, at most ``record_length`` recorded; 0: nothing recorded, e.g. an offline map used
    as is) and returns ``(state, TrainingTrace)``: each value, their moving average
    (``LOSS_SMOOTHING``), and whether every value and the final state's parameters and optimiser
    states are finite (an overflowing Adam moment would poison a warm start). ``state`` has
    ``params``, whose dtype the record takes."""

    def body(iteration, carry):
        state, loss, smoothed, finite = carry
        state, value = step(iteration, state)
        if record_length:
            loss = loss.at[iteration].set(value, mode="drop")
        smoothed = jnp.where(
            iteration == 0, value, LOSS_SMOOTHING * smoothed + (1 - LOSS_SMOOTHING) * value
        )
        return state, loss, smoothed, finite & jnp.isfinite(value)

    dtype = jax.tree.leaves(state.params)[0].dtype
    carry = (state, jnp.full((record_length,), jnp.inf, dtype), jnp.zeros((), dtype), jnp.array(True))
    state, loss, smoothed, finite = jax.lax.fori_loop(0, num_iterations, body, carry)
    leaves = [leaf for leaf in jax.tree.leaves(state) if jnp.issubdtype(leaf.dtype, jnp.inexact)]
    state_finite = jnp.all(jnp.array([jnp.all(jnp.isfinite(leaf)) for leaf in leaves]))
    loss = jnp.where(jnp.isfinite(loss), loss, jnp.inf)
    return state, TrainingTrace(loss, smoothed, finite & state_finite)
