"""Argument checks at the API boundary: one place, one wording, errors that name the argument.

Numbers may be traced (a builder called inside ``jax.vmap`` or ``jax.jit``): a traced value
cannot be checked at build time and passes through unchanged (its range is the caller's
responsibility, as for any traced argument); a concrete value is checked, and a Python number
is returned as a Python float so that the compiled programs do not depend on how it was given.
"""

from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

__all__ = [
    "check_broadcastable",
    "check_finite_array",
    "check_int",
    "check_number",
    "is_traced",
]


def is_traced(value: Any) -> bool:
    """True for a value whose number is unknown at build time (inside jit / vmap / grad)."""
    return isinstance(value, jax.core.Tracer)


def check_int(name: str, value: Any, minimum: int = 1) -> int:
    """A Python int >= ``minimum`` (structure: counts, widths, iterations), else ValueError."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        kind = "a positive int" if minimum == 1 else f"an int >= {minimum}"
        raise ValueError(f"{name} must be {kind}, got {value!r}")
    return int(value)


def check_number(
    name: str,
    value: Any,
    minimum: float | None = None,
    maximum: float | None = None,
    strict_minimum: bool = False,
    finite: bool = True,
):
    """A real scalar setting: a traced one as it is, a concrete one checked against
    ``[minimum, maximum]`` (``(minimum, maximum]`` with ``strict_minimum``) and returned as a
    Python float (also a concrete scalar array: a weakly typed leaf, so that 1.1 and
    ``jnp.float32(1.1)`` share one compiled program and take the filter's precision)."""
    if is_traced(value):
        if jnp.ndim(value) != 0:
            raise ValueError(f"{name} must be a scalar, got shape {jnp.shape(value)}")
        return value
    if isinstance(value, bool) or not (
        isinstance(value, (int, float, np.integer, np.floating))
        or (hasattr(value, "dtype") and jnp.ndim(value) == 0)
    ):
        raise TypeError(f"{name} must be a real number (or a scalar array), got {value!r}")
    number = float(value)
    lower_ok = minimum is None or (number > minimum if strict_minimum else number >= minimum)
    if (
        math.isnan(number)
        or (finite and math.isinf(number))
        or not lower_ok
        or (maximum is not None and number > maximum)
    ):
        bounds = []
        if minimum is not None:
            bounds.append(f"{'>' if strict_minimum else '>='} {minimum:g}")
        if maximum is not None:
            bounds.append(f"<= {maximum:g}")
        what = " and ".join(bounds) if bounds else "a number"
        if finite and math.isinf(number) and lower_ok and (maximum is None or number <= maximum):
            what = "finite"
        raise ValueError(f"{name} must be {what}, got {value!r}")
    return number


def check_finite_array(name: str, value: Any, shape: tuple[int, ...] | None = None):
    """Shape check (if ``shape``), and a concrete array must be finite (NaN or inf raises)."""
    if shape is not None and tuple(jnp.shape(value)) != tuple(shape):
        raise ValueError(f"{name} must have shape {tuple(shape)}, got {tuple(jnp.shape(value))}")
    if not is_traced(value) and not bool(np.all(np.isfinite(np.asarray(value)))):
        raise ValueError(f"{name} must be finite (it holds NaN or inf)")
    return value


def check_broadcastable(first_name: str, first: Any, second_name: str, second: Any,
                        same_last_axis: bool = False) -> None:
    """ValueError naming both arguments unless their shapes broadcast (and, with
    ``same_last_axis``, have at least one axis and equal last axes: e.g. state vectors)."""
    first_shape, second_shape = tuple(jnp.shape(first)), tuple(jnp.shape(second))
    try:
        np.broadcast_shapes(first_shape, second_shape)
        compatible = not same_last_axis or (
            first_shape and second_shape and first_shape[-1] == second_shape[-1]
        )
    except ValueError:
        compatible = False
    if not compatible:
        rule = "broadcast against each other with equal last axes" if same_last_axis else "broadcast"
        raise ValueError(
            f"{first_name} and {second_name} must {rule}, got shapes {first_shape} and {second_shape}"
        )
