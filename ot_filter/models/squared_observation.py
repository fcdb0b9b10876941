"""The chapter's bimodal examples: a squared observation of each coordinate.

Static example (chapter, Sec. "Numerical demonstration"):

    X ~ N(0, I_n),   Y = 0.5 X (.) X + lambda_w W           (observation_scale=0.5, static=True)

Dynamic example (chapter, eq. model-example):

    X_t = (1 - alpha) X_{t-1} + 2 lambda V_t,   X_0 ~ N(0, I_n),
    Y_t = X_t (.) X_t + lambda W_t                          (observation_scale=1.0)

Observing x^2 loses the sign, so every coordinate's posterior has two mirror-image modes at
+-sqrt(y / scale): EnKF cannot represent them, SIR collapses onto one in high dimension.
Coordinates are independent, so exact posteriors factorise into 1-D ones. The model carries a
geometry (coordinate i and component i at position i on a line) for localised updates.
"""

from __future__ import annotations

import jax
import numpy as np

from ot_filter.lib.static import bind
from ot_filter.localisation import points
from ot_filter.lib.validation import check_number, is_traced
from ot_filter.model import StateSpaceModel
from ot_filter.models._gaussian_observation import (
    check_nonnegative,
    check_positive,
    with_gaussian_observation,
)


def squared_observation(
    dim: int = 2,
    alpha: float = 0.1,
    noise: float = 0.1**0.5,
    observation_scale: float = 1.0,
    static: bool = False,
    process_noise_std: float | None = None,
) -> StateSpaceModel:
    """Builds the squared-observation model.

    Args:
      dim: state dimension n (= observation dimension).
      alpha: damping of the dynamics, ``X_t = (1 - alpha) X_{t-1} + ...``.
      noise: lambda, the observation noise std (the static example uses lambda_w 0.4 or 0.04).
      observation_scale: the factor in ``Y = scale * X (.) X + noise * W`` (0.5 static, 1 dynamic).
      static: if True the state does not move (``X_t = X_{t-1}``): the static Bayes problem.
      process_noise_std: std of the dynamics' noise; default ``2 * noise`` as in the chapter.
    """
    if not isinstance(dim, int) or dim < 1:
        raise ValueError(f"dim must be a positive int, got {dim!r}")
    alpha = check_nonnegative("alpha", alpha)
    noise = check_positive("noise", noise)
    scale = check_number("observation_scale", observation_scale)
    if not is_traced(scale) and scale == 0.0:
        raise ValueError(f"observation_scale must be finite and non-zero, got {observation_scale}")
    if process_noise_std is None:
        process_noise_std = 2.0 * noise
    process_std = check_nonnegative("process_noise_std", process_noise_std)
    decay = 1.0 - alpha
    return with_gaussian_observation(
        bind(_sample_initial, dim=dim),
        bind(_sample_transition, (decay, process_std), static=bool(static)),
        bind(_observation_function, scale),
        dim,
        noise,
        # Component i observes coordinate i: positions on a line (localised updates with radius
        # 0 then treat the coordinates as the independent problems they are).
        geometry=points(np.arange(dim), np.arange(dim)),
    )


# Module-level functions bound to their numbers (traced leaves) and structure (lib.static.bind).


def _sample_initial(key, *, dim):
    return jax.random.normal(key, (dim,))


def _sample_transition(numbers, key, x, *, static):
    if static:
        return x
    decay, process_std = numbers
    return decay * x + process_std * jax.random.normal(key, x.shape, x.dtype)


def _observation_function(scale, x):
    return scale * x * x
