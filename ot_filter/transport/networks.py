"""The two networks of the OT Bayes update (chapter, Sec. "Bayes update with optimal transport").

    f(x, y) -> scalar        the Kantorovich potential, maximised
    T(x, y) -> x'            the conditional transport map, minimised; T = x + ResNet([x; y])

Both read the concatenation [x; y] through an input layer followed by ``num_blocks`` residual
blocks (two dense layers with a skip connection), as in the authors' code. T is a residual on its
input: its last layer starts at zero, so an untrained T is the identity (or the EnKF layer's
update when that layer is on, see ``updates/ot.py``), a sensible first guess for a Bayes update.
Inputs are expected standardised (the update does it); nothing here depends on the data scale.
"""

from __future__ import annotations

from typing import Callable

import flax.linen as nn
import jax
import jax.numpy as jnp

Array = jax.Array

ACTIVATIONS: dict[str, Callable[[Array], Array]] = {
    "relu": nn.relu,
    "silu": nn.silu,
    "softplus": nn.softplus,
    "tanh": jnp.tanh,
    "gelu": nn.gelu,
}


class _ResidualMLP(nn.Module):
    width: int
    num_blocks: int
    out_features: int
    activation: str
    zero_output: bool = False

    @nn.compact
    def __call__(self, inputs: Array) -> Array:
        act = ACTIVATIONS[self.activation]
        hidden = act(nn.Dense(self.width)(inputs))
        for _ in range(self.num_blocks):  # unrolled at trace time: depth is static config
            residual = act(nn.Dense(self.width)(hidden))
            residual = nn.Dense(self.width)(residual)
            hidden = act(hidden + residual)
        kernel_init = nn.initializers.zeros if self.zero_output else nn.initializers.lecun_normal()
        return nn.Dense(self.out_features, kernel_init=kernel_init)(hidden)


class PotentialNetwork(nn.Module):
    """``f(x[..., n], y[..., m]) -> [...]``."""

    width: int = 32
    num_blocks: int = 1
    activation: str = "relu"

    @nn.compact
    def __call__(self, x: Array, y: Array) -> Array:
        inputs = jnp.concatenate([x, y], axis=-1)
        return _ResidualMLP(self.width, self.num_blocks, 1, self.activation)(inputs)[..., 0]


class TransportNetwork(nn.Module):
    """``T(x[..., n], y[..., m]) = x + ResNet([x; y]) -> [..., n]`` (identity at initialisation)."""

    width: int = 32
    num_blocks: int = 1
    activation: str = "relu"

    @nn.compact
    def __call__(self, x: Array, y: Array) -> Array:
        inputs = jnp.concatenate([x, y], axis=-1)
        mlp = _ResidualMLP(self.width, self.num_blocks, x.shape[-1], self.activation, zero_output=True)
        return x + mlp(inputs)


# Public name (flax names parameters after the class, so the class keeps its original name).
ResidualMLP = _ResidualMLP
