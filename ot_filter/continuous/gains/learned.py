"""A learned gain: a neural network phi trained on the weak form of the Poisson equation.

The chapter (Sec. "Relationship to the FPF Bayes update") shows that the first-order term of the
OT objective for an observation increment is maximised by the FPF gain K = grad phi, where

    phi = argmax_phi  E[ -0.5 |grad phi(X)|^2 + phi(X) (h(X) - h_hat) ],

the weak form of -(1/p) div(p grad phi) = h - h_hat. Here phi: R^n -> R^m (one potential per
observation component) is a residual MLP with a smooth activation (the correction needs second
derivatives), trained on the particles with optax, warm-started across time steps, with the
expectation replaced by the ensemble (or mini-batch) average.

Scales: the network sees standardised particles z = (x - mean) / std and component-wise
standardised h, and phi_k = s^2 std(h_k) psi_k(z) with s^2 the mean variance, so that psi = O(1)
whatever the data's units.

Robustness: after training, the objective is evaluated on freshly jittered particles with each
psi_k rescaled by its best multiple (a free line search). The constant gain is the exact maximiser
over linear phi, so its objective value is a floor any working network must reach (up to
``fallback_margin`` of it); a network below it (diverged, or overfitting single particles), or
not finite, is replaced by the constant gain for that step (``info.fallback``).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import optax
import flax.linen as nn

from ot_filter.continuous.gains.base import Gain, GainOutput, constant_gain_output, gain_and_correction
from ot_filter.lib.fallback import use_where
from ot_filter.lib.static import bind
from ot_filter.lib.validation import check_int, check_number
from ot_filter.transport.networks import ACTIVATIONS, ResidualMLP

Array = jax.Array

__all__ = ["LearnedGainInfo", "LearnedGainSettings", "LearnedGainState", "learned_gain"]


class LearnedGainSettings(NamedTuple):
    """The learned gain's numbers (traced: ``vmap`` over them runs in one program)."""

    learning_rate: Array  # Adam's (default optimiser only)
    fallback_margin: Array
    smoothing: Array


class LearnedGainState(NamedTuple):
    params: Any
    optimizer_state: Any
    step: Array  # number of updates done (the first one trains longer)


class LearnedGainInfo(NamedTuple):
    objective: Array  # max_c E[-0.5 |grad c psi|^2 + c psi (h - h_hat)] on fresh jittered points
    constant_gain_objective: Array  # the same objective of the constant gain (the floor)
    fallback: Array  # bool, the constant gain was used instead


class _Potential(nn.Module):
    width: int
    num_blocks: int
    out_features: int
    activation: str

    @nn.compact
    def __call__(self, z):
        return ResidualMLP(self.width, self.num_blocks, self.out_features, self.activation)(z)


def learned_gain(
    num_iterations: int | tuple[int, int] = (500, 50),
    width: int = 32,
    num_blocks: int = 1,
    activation: str = "tanh",
    optimizer: optax.GradientTransformation | None = None,
    batch_size: int | None = None,
    warm_start: bool = True,
    fallback_margin: float = 0.05,
    smoothing: float = 0.2,
    learning_rate: float = 1e-3,
) -> Gain:
    """Builds the learned gain.

    Args:
      num_iterations: optimiser steps per time step, or ``(first, later)``: ``first`` at the first
        step (from scratch), ``later`` at the warm-started ones.
      width, num_blocks, activation: the network (a smooth activation: tanh, silu, softplus, gelu).
      optimizer: an optax transformation replacing the default Adam(``learning_rate``) (static).
      batch_size: particles per step (None: the whole ensemble).
      warm_start: start from the previous step's weights and optimiser state.
      fallback_margin: fall back to the constant gain when the trained objective is below the
        constant gain's by more than this fraction of its magnitude.
      smoothing: the expectation is taken over the particles jittered by this many standard
        deviations (fresh Gaussian noise every step): on the bare empirical measure the objective
        is unbounded (a narrow bump of phi at one particle has zero gradient there), so a flexible
        network overfits outliers and the gain blows up; jittering makes it a proper density.
      learning_rate: the default Adam's learning rate.

    ``learning_rate``, ``fallback_margin`` and ``smoothing`` may be traced (a sweep over them
    vmaps into one program); the rest is structure.
    """
    if isinstance(num_iterations, tuple):
        if len(num_iterations) != 2:
            raise ValueError(f"num_iterations must be an int or (first, later), got {num_iterations!r}")
        first, later = num_iterations
    else:
        first = later = num_iterations
    if activation not in ACTIVATIONS or activation == "relu":
        smooth = sorted(a for a in ACTIVATIONS if a != "relu")
        raise ValueError(f"activation must be a smooth one of {smooth}, got {activation!r}")
    if batch_size is not None:
        batch_size = check_int("batch_size", batch_size, minimum=2)
    if optimizer is not None and not isinstance(optimizer, optax.GradientTransformation):
        raise TypeError(f"optimizer must be an optax.GradientTransformation, got {type(optimizer).__name__}")
    settings = LearnedGainSettings(
        learning_rate=check_number("learning_rate", learning_rate, 0.0, strict_minimum=True),
        fallback_margin=check_number("fallback_margin", fallback_margin, 0.0),
        smoothing=check_number("smoothing", smoothing, 0.0),
    )
    structure = dict(
        first=check_int("num_iterations (first)", first),
        later=check_int("num_iterations (later)", later),
        width=check_int("width", width),
        num_blocks=check_int("num_blocks", num_blocks, minimum=0),
        activation=activation,
        optimizer=optimizer,
        batch_size=batch_size,
        warm_start=bool(warm_start),
    )
    return Gain(bind(_learned_init, settings, **structure), bind(_learned_apply, settings, **structure))


def _optimizer(settings, optimizer):
    """The given optax transformation, else Adam at the (traced) learning rate."""
    return optax.adam(settings.learning_rate) if optimizer is None else optimizer


def _learned_init(settings, key, particles, h_values, *, first, later, width, num_blocks, activation,
                  optimizer, batch_size, warm_start):
    network = _Potential(width, num_blocks, h_values.shape[1], activation)
    params = network.init(key, jnp.zeros((1, particles.shape[1]), particles.dtype))
    return LearnedGainState(params, _optimizer(settings, optimizer).init(params), jnp.zeros((), jnp.int32))


def _learned_apply(settings, key, state, particles, h_values, *, first, later, width, num_blocks,
                   activation, optimizer, batch_size, warm_start):
    fallback_margin, smoothing = settings.fallback_margin, settings.smoothing
    structure = dict(first=first, later=later, width=width, num_blocks=num_blocks, activation=activation,
                     optimizer=optimizer, batch_size=batch_size, warm_start=warm_start)
    optimizer = _optimizer(settings, optimizer)
    num, n = particles.shape
    m = h_values.shape[1]
    network = _Potential(width, num_blocks, m, activation)
    mean = jnp.mean(particles, axis=0)
    std = jnp.maximum(jnp.std(particles, axis=0), 1e-12)
    mean_variance = jnp.mean(std**2)
    centred_h = h_values - jnp.mean(h_values, axis=0)
    h_std = jnp.maximum(jnp.std(h_values, axis=0), 1e-12)
    normalised_h = centred_h / h_std
    ratio = jnp.sqrt(mean_variance) / std  # d psi / d x in units where phi ~ s^2 std(h) psi

    def psi(params, z):
        return network.apply(params, z[None])[0]  # [m]

    def objective(params, z, hn):
        jac = jax.vmap(jax.jacfwd(lambda zz: psi(params, zz)))(z)  # [B, m, n] d psi / dz
        scaled = jac * ratio
        values = jax.vmap(lambda zz: psi(params, zz))(z)  # [B, m]
        return jnp.mean(-0.5 * jnp.sum(scaled**2, axis=(1, 2)) + jnp.sum(values * hn, axis=1))

    z_all = (particles - mean) / std
    train_key, check_key, init_key = jax.random.split(key, 3)
    params = state.params
    opt_state = state.optimizer_state
    if not warm_start:
        params = _learned_init(settings, init_key, particles, h_values, **structure).params
        opt_state = optimizer.init(params)
    trips = jnp.where(state.step == 0, first, later)

    def train_step(i, carry):
        params, opt_state = carry
        step_key = jax.random.fold_in(train_key, i)
        if batch_size is None or batch_size >= num:
            z, hn = z_all, normalised_h
        else:
            index = jax.random.choice(step_key, num, (min(batch_size, num),), replace=False)
            z, hn = z_all[index], normalised_h[index]
        z = z + smoothing * jax.random.normal(jax.random.fold_in(step_key, 1), z.shape, z.dtype)
        grads = jax.grad(lambda p: -objective(p, z, hn))(params)
        updates, opt_state = optimizer.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), opt_state

    params, opt_state = jax.lax.fori_loop(0, trips, train_step, (params, opt_state))
    # Validation on a fresh jitter, and the best multiple c_k of each psi_k there: the
    # objective along psi -> c psi is c B - c^2 A / 2, maximised at c = B / A with value
    # B^2 / (2 A). A network that overfits single particles (large gradients between them) or
    # diverged gets a small c and a low value, and the constant-gain floor below catches it.
    z_check = z_all + smoothing * jax.random.normal(check_key, z_all.shape, z_all.dtype)
    jac = jax.vmap(jax.jacfwd(lambda zz: psi(params, zz)))(z_check) * ratio  # [N, m, n]
    psi_values = jax.vmap(lambda zz: psi(params, zz))(z_check)  # [N, m]
    curvature = jnp.mean(jnp.sum(jac**2, axis=2), axis=0)  # A_k
    correlation = jnp.mean(psi_values * normalised_h, axis=0)  # B_k
    healthy = jnp.isfinite(curvature) & jnp.isfinite(correlation) & (curvature > 0)
    multiplier = jnp.where(healthy, correlation / jnp.where(healthy, curvature, 1.0), 0.0)
    value = jnp.sum(jnp.where(healthy, 0.5 * multiplier * correlation, -jnp.inf))
    # The constant gain is the best linear phi: its objective is 0.5 |Cov(x / s, h_n)|^2 in
    # these units (s^2 the mean variance).
    linear = (particles - mean).T @ normalised_h / (num * jnp.sqrt(mean_variance))  # [n, m]
    constant_value = 0.5 * jnp.sum(linear**2)
    scale = mean_variance * h_std * multiplier  # [m]: phi_k = s^2 std(h_k) c_k psi_k

    def field(x):
        jac = jax.jacfwd(lambda xx: psi(params, (xx - mean) / std))(x)  # [m, n]
        return (jac * scale[:, None]).T  # [n, m]

    gain, correction = jax.vmap(lambda x: gain_and_correction(field, x))(particles)
    usable = (
        jnp.isfinite(value)
        & (value >= constant_value - fallback_margin * jnp.abs(constant_value))
        & jnp.all(jnp.isfinite(gain))
        & jnp.all(jnp.isfinite(correction))
    )
    output = use_where(usable, GainOutput(gain, correction), constant_gain_output(particles, h_values))
    # A failed training restarts from its last finite weights next step.
    finite = jnp.isfinite(value)
    params = use_where(finite, params, state.params)
    opt_state = use_where(finite, opt_state, state.optimizer_state)
    new_state = LearnedGainState(params, opt_state, state.step + 1)
    info = LearnedGainInfo(value, constant_value, ~usable)
    return output, new_state, info

