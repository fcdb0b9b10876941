"""Continuous-time models (the chapter's eqs. model-dyn-cont / model-obs-cont) and their simulation.

    dX_t = a(X_t) dt + b(X_t) dB_t,        X_0 ~ pi_0
    dY_t = h(X_t) dt + sigma dW_t          (B: q-dim., W: m-dim. standard Brownian motions)

A model is given by per-state functions (``x[n]``), like ``StateSpaceModel``; the library vmaps
them over particles. On a time grid of step dt, the path is simulated by Euler-Maruyama and the
observation is delivered as increments

    dY_k = Y_{t_{k+1}} - Y_{t_k} ~= h(X_{t_k}) dt + sigma sqrt(dt) W_k,      k = 0..T-1,

so increment k is assimilated at the state X_{t_k} (the left end of its interval, as Ito
integrals are) and the filter then moves to t_{k+1}. ``discretise`` turns a model into the
discrete-time ``StateSpaceModel`` with exactly this (Euler-Maruyama) transition and increment
likelihood, so that EnKF, SIR and OT run on the same data as the FPF (``run_filter`` with
``update_first=True``).
"""

from __future__ import annotations

from functools import partial
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ot_filter.lib.validation import check_int
from ot_filter.model import StateSpaceModel

Array = jax.Array

__all__ = ["SDEModel", "SDEPath", "check_time_step", "discretise", "sde_dimensions", "simulate_sde"]


class SDEModel(NamedTuple):
    """A continuous-time model ``dX = a(X) dt + b(X) dB``, ``dY = h(X) dt + sigma dW``.

    Attributes:
      drift: ``x[n] -> a(x)[n]``.
      diffusion: ``x[n] -> b(x)``, either ``[n, q]`` (B is q-dimensional) or ``[n]`` (diagonal,
        q = n, one independent Brownian motion per component).
      observation_function: ``x[n] -> h(x)[m]``.
      sample_initial: ``key -> x[n]``, a draw from pi_0.
      observation_noise_std: sigma, a scalar or ``[m]`` (independent noise per component); the
        filters whiten with it (dY / sigma, h / sigma).
      parameters: optional pytree a built-in model keeps (e.g. the matrices of the linear model
        for the Kalman-Bucy filter).
    """

    drift: Callable[[Array], Array]
    diffusion: Callable[[Array], Array]
    observation_function: Callable[[Array], Array]
    sample_initial: Callable[[Array], Array]
    observation_noise_std: Any = 1.0
    parameters: Any = None


_FUNCTION_FIELDS = ("drift", "diffusion", "observation_function", "sample_initial")

# Functions are static aux data (hashable by identity); arrays are traced leaves.
jax.tree_util.register_pytree_node(
    SDEModel,
    lambda model: (
        (model.observation_noise_std, model.parameters),
        tuple(getattr(model, name) for name in _FUNCTION_FIELDS),
    ),
    lambda static, children: SDEModel(*static, *children),
)


class SDEPath(NamedTuple):
    """A simulated path on the grid t_k = k dt, k = 0..T."""

    times: Array  # [T + 1]
    states: Array  # [T + 1, n]  X_{t_0} .. X_{t_T}
    increments: Array  # [T, m]  dY_0 .. dY_{T-1}


def sde_dimensions(model: SDEModel) -> tuple[int, int, int]:
    """Returns ``(n, m, q)`` (state, observation, Brownian dimensions), checking every shape."""
    if not isinstance(model, SDEModel):
        raise TypeError(f"model must be an SDEModel, got {type(model).__name__}")
    try:
        x = jax.eval_shape(model.sample_initial, jax.random.key(0))
    except Exception as error:  # noqa: BLE001 - re-raised with the argument named
        raise TypeError(f"model.sample_initial(key) failed: {error}") from error
    if x.ndim != 1:
        raise ValueError(f"model.sample_initial must return a state x[n], got shape {x.shape}")
    n = x.shape[0]
    drift = jax.eval_shape(model.drift, x)
    if drift.shape != (n,):
        raise ValueError(f"model.drift must return shape ({n},) (the state's), got {drift.shape}")
    diffusion = jax.eval_shape(model.diffusion, x)
    if diffusion.shape == (n,):
        q = n
    elif diffusion.ndim == 2 and diffusion.shape[0] == n and diffusion.shape[1] >= 1:
        q = diffusion.shape[1]
    else:
        raise ValueError(
            f"model.diffusion must return a matrix [n={n}, q] or a diagonal [n={n}], got shape "
            f"{diffusion.shape}"
        )
    hx = jax.eval_shape(model.observation_function, x)
    if hx.ndim != 1 or hx.shape[0] < 1:
        raise ValueError(
            f"model.observation_function must return h(x)[m], got shape {hx.shape}"
        )
    m = hx.shape[0]
    std = model.observation_noise_std
    if np.ndim(std) not in (0, 1) or (np.ndim(std) == 1 and np.shape(std) != (m,)):
        raise ValueError(
            f"model.observation_noise_std must be a scalar or have shape ({m},), got shape "
            f"{np.shape(std)}"
        )
    if not isinstance(std, jax.core.Tracer) and not np.all(np.asarray(std) > 0):
        raise ValueError(f"model.observation_noise_std must be > 0, got {std}")
    return n, m, q


def check_time_step(dt) -> None:
    """dt must be a positive scalar (checked when concrete; a traced dt is taken as is)."""
    if np.ndim(dt) != 0:
        raise ValueError(f"dt must be a scalar, got shape {np.shape(dt)}")
    if not isinstance(dt, jax.core.Tracer) and not float(dt) > 0:  # also rejects NaN
        raise ValueError(f"dt must be > 0, got {dt}")


def diffusion_increment(model: SDEModel, x: Array, noise: Array) -> Array:
    """``b(x) @ noise`` for a matrix diffusion, ``b(x) * noise`` for a diagonal one."""
    b = model.diffusion(x)
    return b @ noise if b.ndim == 2 else b * noise


def euler_maruyama_step(key: Array, model: SDEModel, x: Array, dt) -> Array:
    """One Euler-Maruyama step ``x + a(x) dt + b(x) sqrt(dt) xi`` of one state x[n]."""
    b_shape = jax.eval_shape(model.diffusion, x).shape
    noise = jax.random.normal(key, (b_shape[-1],), x.dtype)
    return x + model.drift(x) * dt + diffusion_increment(model, x, noise) * jnp.sqrt(dt)


def simulate_sde(
    key: Array, model: SDEModel, dt: float, num_steps: int, substeps: int = 1
) -> SDEPath:
    """Simulates the state and the observation increments by Euler-Maruyama.

    Args:
      key: PRNG key.
      model: the SDE model.
      dt: time step of the observation grid (> 0).
      num_steps: T, the number of increments (static).
      substeps: the truth is integrated with step dt / substeps and the increments summed over
        each grid interval (a finer truth for time-step convergence studies; static).

    Returns:
      ``SDEPath(times[T + 1], states[T + 1, n], increments[T, m])``.
    """
    check_time_step(dt)
    num_steps, substeps = check_int("num_steps", num_steps), check_int("substeps", substeps)
    sde_dimensions(model)
    return _simulate_sde(key, model, dt, num_steps, substeps)


@partial(jax.jit, static_argnums=(3, 4))
def _simulate_sde(key, model, dt, num_steps, substeps):
    init_key, steps_key = jax.random.split(key)
    x0 = model.sample_initial(init_key)
    fine_dt = dt / substeps
    std = jnp.asarray(model.observation_noise_std, x0.dtype)

    def fine_step(x, step_key):
        state_key, noise_key = jax.random.split(step_key)
        hx = model.observation_function(x)
        increment = hx * fine_dt + std * jnp.sqrt(fine_dt) * jax.random.normal(noise_key, hx.shape, hx.dtype)
        return euler_maruyama_step(state_key, model, x, fine_dt), increment

    def step(x, step_key):
        x, increments = jax.lax.scan(fine_step, x, jax.random.split(step_key, substeps))
        return x, (x, jnp.sum(increments, axis=0))

    _, (states, increments) = jax.lax.scan(step, x0, jax.random.split(steps_key, num_steps))
    times = jnp.arange(num_steps + 1, dtype=x0.dtype) * dt
    return SDEPath(times, jnp.concatenate([x0[None], states]), increments)


def discretise(model: SDEModel, dt: float) -> StateSpaceModel:
    """The Euler-Maruyama discretisation as a discrete-time ``StateSpaceModel``.

    Transition ``x + a(x) dt + b(x) sqrt(dt) xi``; observation the increment
    ``h(x) dt + sigma sqrt(dt) W`` with its Gaussian likelihood (for SIR) and ``h dt``,
    ``R = sigma^2 dt I`` (for the EnKF). Filter it with ``run_filter(..., update_first=True)``:
    increment k is then assimilated at X_{t_k} before the step to t_{k+1}, as ``simulate_sde``
    generates it and as the FPF does.
    """
    check_time_step(dt)
    _, m, _ = sde_dimensions(model)
    std = jnp.broadcast_to(jnp.asarray(model.observation_noise_std, float), (m,))
    increment_std = std * jnp.sqrt(dt)
    log_normaliser = -jnp.sum(0.5 * jnp.log(2 * jnp.pi) + jnp.log(increment_std))

    def sample_transition(key, x):
        return euler_maruyama_step(key, model, x, dt)

    def observation_function(x):
        return model.observation_function(x) * dt

    def sample_observation(key, x):
        hx = observation_function(x)
        return hx + increment_std.astype(hx.dtype) * jax.random.normal(key, hx.shape, hx.dtype)

    def log_likelihood(y, x):
        return log_normaliser - 0.5 * jnp.sum(((y - observation_function(x)) / increment_std) ** 2)

    return StateSpaceModel(
        sample_initial=model.sample_initial,
        sample_transition=sample_transition,
        sample_observation=sample_observation,
        log_likelihood=log_likelihood,
        observation_function=observation_function,
        observation_noise_cov=jnp.diag(increment_std**2),
        parameters=None,
    )
