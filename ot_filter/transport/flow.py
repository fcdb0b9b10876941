"""Conditional flow matching: a transport from the prior to the posterior learned by regression.

The OT update learns its map T(x, y) by a max-min game (``saddle.py``), whose iterates do not
settle (``docs/ot_at_scale.md``, "Where OT still loses"). Flow matching learns a transport by
least squares instead. With X0 ~ p(x) drawn independently of a joint pair (X1, Y) ~ p(x, y),
and x_t = (1 - t) X0 + t X1 on t ~ U(0, 1), the velocity field

    v(x, t, y) = argmin E |v(x_t, t, Y) - (X1 - X0)|^2

carries, for every y, the law of X0 (the prior: X0 is independent of Y) at t = 0 to the law of
X1 given Y = y (the posterior) at t = 1 (Lipman et al. 2023, Liu et al. 2023, conditioned on y as
in Wildberger et al. 2023's flow-matching posterior estimation). Integrating dx/dt = v(x, t, y)
from a prior particle is a deterministic map of it: the Bayes update moves each particle along
the flow. The map is not the optimal-transport map (the coupling is independent), only a
transport.

Here: the velocity network, the loss, the ODE solver and the training loop, all in standardised
coordinates; ``updates/flow_matching.py`` assembles them into a ``BayesUpdate``.
"""

from __future__ import annotations

import math
from typing import Callable, NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp
import optax

from ot_filter.transport.networks import ACTIVATIONS
from ot_filter.transport.saddle import Batch, TrainingTrace, recorded_loop

Array = jax.Array

__all__ = [
    "FlowTraining",
    "VelocityNetwork",
    "cosine_factor",
    "flow_matching_loss",
    "init_flow",
    "integrate_flow",
    "train_flow",
]

# Frequencies (times pi) of the Fourier features of t: enough to let v change fast near t = 1,
# where the flow sharpens the posterior's modes.
TIME_FREQUENCIES = 4
# Adam's moments without its rate: each step is scaled by the cosine-decayed rate (train_flow).
ADAM = optax.scale_by_adam()


class VelocityNetwork(nn.Module):
    """``v(x[..., n], t[...], y[..., m]) -> [..., n]``: an MLP of ``depth`` hidden layers on
    [x; y; t; sin(k pi t); cos(k pi t)]. Its last layer starts at zero: an untrained flow is the
    identity map (the prior unchanged)."""

    width: int = 256
    depth: int = 3
    activation: str = "silu"

    @nn.compact
    def __call__(self, x: Array, t: Array, y: Array) -> Array:
        act = ACTIVATIONS[self.activation]
        t = jnp.broadcast_to(t, x.shape[:-1])[..., None]
        angles = jnp.pi * jnp.arange(1, TIME_FREQUENCIES + 1, dtype=x.dtype) * t
        hidden = jnp.concatenate([x, y, t, jnp.sin(angles), jnp.cos(angles)], axis=-1)
        for _ in range(self.depth):  # unrolled at trace time: depth is static config
            hidden = act(nn.Dense(self.width)(hidden))
        return nn.Dense(x.shape[-1], kernel_init=nn.initializers.zeros)(hidden)


class FlowTraining(NamedTuple):
    params: dict  # the velocity network's parameters
    opt_state: optax.OptState  # Adam's moments (scale_by_adam: the rate is applied per step)


def flow_matching_loss(velocity: Callable, batch: Batch, t: Array) -> Array:
    """Mean over the batch of |v(x_t, t, y) - (x1 - x0)|^2 with x1, y = ``batch.x``, ``batch.y``
    (joint pairs) and x0 = ``batch.xbar`` (independent copies), t[B] in [0, 1]."""
    x0, x1 = batch.xbar, batch.x
    xt = (1.0 - t)[:, None] * x0 + t[:, None] * x1
    return jnp.mean(jnp.sum((velocity(xt, t, batch.y) - (x1 - x0)) ** 2, axis=-1))


def integrate_flow(velocity: Callable, x: Array, y: Array, num_steps: int) -> Array:
    """x(1) from x(0) = ``x[N, n]`` along dx/dt = v(x, t, y) with ``y[N, m]``: Heun's method
    (second order) on ``num_steps`` equal steps."""
    dt = 1.0 / num_steps

    def step(i, x):
        t = jnp.asarray(i, x.dtype) * dt
        v0 = velocity(x, t, y)
        v1 = velocity(x + dt * v0, t + dt, y)
        return x + 0.5 * dt * (v0 + v1)

    return jax.lax.fori_loop(0, num_steps, step, x)


def cosine_factor(iteration: Array, budget: Array, dtype=jnp.float32) -> Array:
    """The learning rate's factor at ``iteration`` of ``budget``: 1 -> 0 on half a cosine, so that
    each training (a warm-started filter step too) ends on small steps whatever its budget."""
    fraction = jnp.asarray(iteration, dtype) / jnp.maximum(jnp.asarray(budget, dtype), 1.0)
    return 0.5 * (1.0 + jnp.cos(math.pi * fraction))


def train_flow(key: Array, training: FlowTraining, sample_batch: Callable[[Array], Batch],
               num_iterations: Array | int, *, network: VelocityNetwork, learning_rate: Array,
               record_length: int) -> tuple[FlowTraining, TrainingTrace]:
    """``num_iterations`` Adam steps on the flow-matching loss (traced allowed, at most
    ``record_length``), the rate ``learning_rate`` decayed to 0 on a cosine over them.
    ``sample_batch(key) -> Batch`` draws joint pairs and independent copies (standardised)."""
    def loss_of(params, batch, t):
        return flow_matching_loss(lambda x, s, y: network.apply(params, x, s, y), batch, t)

    def step(iteration, training):
        batch_key, time_key = jax.random.split(jax.random.fold_in(key, iteration))
        batch = sample_batch(batch_key)
        t = jax.random.uniform(time_key, (batch.x.shape[0],), batch.x.dtype)
        value, grads = jax.value_and_grad(loss_of)(training.params, batch, t)
        updates, opt_state = ADAM.update(grads, training.opt_state, training.params)
        rate = learning_rate * cosine_factor(iteration, num_iterations, value.dtype)
        updates = jax.tree.map(lambda u: (-rate * u).astype(u.dtype), updates)
        return FlowTraining(optax.apply_updates(training.params, updates), opt_state), value

    return recorded_loop(step, training, num_iterations, record_length)


def init_flow(key: Array, network: VelocityNetwork, n: int, m: int, dtype) -> FlowTraining:
    """Fresh parameters (in the data's dtype) and Adam's moments."""
    params = network.init(key, jnp.zeros((1, n), dtype), jnp.zeros((1,), dtype), jnp.zeros((1, m), dtype))
    params = jax.tree.map(lambda leaf: leaf.astype(dtype), params)
    return FlowTraining(params, ADAM.init(params))
