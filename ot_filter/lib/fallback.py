"""The fallback combinator: keep a result where it is usable, a fallback where it failed.

Learned parts (the OT map, the FPF's kernel and learned gains) can fail: a diverged training, a
fixed point that did not converge, a non-finite gain. Each then uses a safe alternative for that
step (the EnKF update, the constant gain) and often restarts its own state. ``use_where`` writes
that choice once, over whole pytrees, as a ``where`` (both branches are computed: the choice is
traced, and under ``vmap`` a ``cond`` would compute both anyway).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp

__all__ = ["use_where"]


def use_where(usable, value: Any, fallback: Any) -> Any:
    """``value`` where ``usable`` (a bool scalar, or an array broadcasting against the leaves),
    ``fallback`` elsewhere, leaf by leaf over two pytrees of the same structure."""
    return jax.tree.map(lambda new, old: jnp.where(usable, new, old), value, fallback)
