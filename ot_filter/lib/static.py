"""Builders return NamedTuples of pure functions; this module binds those functions to their
configuration so that the result is a pytree: structure static, numbers traced.

``bind(function, settings, **structure)`` returns a ``jax.tree_util.Partial`` whose leaves are the
numbers in ``settings`` (a NamedTuple of scalars: inflation, jitter, learning rates, ...) and whose
static part is ``function`` with the keyword ``structure`` (scheme names, counts, widths),
compared BY VALUE. Calling it calls ``function(settings, *args, structure..., **kwargs)``.

Consequences, for any builder written this way (``enkf``, ``sir``, ``ot``, the FPF gains):

- ``jax.jit`` / ``run_filter`` see the numbers as traced leaves: a new value reuses the compiled
  program, and ``jax.vmap(lambda a: run_filter(key, model, enkf(inflation=a), ys, N).mean)``
  runs a whole sweep as ONE program;
- two builds with the same structure have equal tree definitions (no recompilation for a
  rebuilt but identical update: no cache of built objects is needed);
- a different structure (``perturbed=False``) is a different program, as it must be.
"""

from __future__ import annotations

import functools
from typing import Any, Callable

import jax

__all__ = ["StaticFunction", "bind", "functions_as_pytrees"]


class StaticFunction(functools.partial):
    """``functools.partial`` of keyword structure, equal (and hashing) by value: the function's
    identity and the keyword values, which must be hashable."""

    def _identity(self):
        return (self.func, self.args, tuple(sorted(self.keywords.items())))

    def __eq__(self, other):
        return type(other) is type(self) and self._identity() == other._identity()

    def __hash__(self):
        return hash(self._identity())

    def __repr__(self):
        settings = ", ".join(f"{name}={value!r}" for name, value in sorted(self.keywords.items()))
        return f"{self.func.__qualname__}({settings})"


_NO_SETTINGS = object()


def bind(function: Callable, settings: Any = _NO_SETTINGS, **structure) -> jax.tree_util.Partial:
    """``function`` with its traced ``settings`` (first positional argument; a pytree of numbers,
    omitted when not given) and its static keyword ``structure`` bound; a pytree whose leaves are
    the settings."""
    static = StaticFunction(function, **structure)
    hash(static)  # fails here, at build time, if some structure is unhashable
    if settings is _NO_SETTINGS:
        return jax.tree_util.Partial(static)
    return jax.tree_util.Partial(static, settings)


def functions_as_pytrees(functions):
    """A NamedTuple of functions (an update, a gain) with every plain function wrapped as a
    leafless ``jax.tree_util.Partial`` (static, compared by identity), so that the whole tuple
    can be a traced argument of a jitted filter; bound functions are kept as they are."""
    wrapped = {
        name: jax.tree_util.Partial(value)
        for name, value in zip(functions._fields, functions)
        if callable(value) and not isinstance(value, jax.tree_util.Partial)
    }
    return functions._replace(**wrapped) if wrapped else functions
