"""The feedback particle filter (FPF) on a time grid: one ``lax.scan`` over the increments.

Each particle follows (chapter, Sec. "Bayes update in feedback particle filter", with dynamics)

    dX^i = a(X^i) dt + b(X^i) dB^i + K(X^i) o (dY - (h(X^i) + h_hat) / 2 dt),

in Stratonovich form. With whitened h / sigma and dY / sigma, a step from t_k to t_{k+1} is the
Euler-Maruyama step of the equivalent Ito SDE,

    X^i <- X^i + a dt + b sqrt(dt) xi^i + K(X^i) dI^i + 0.5 sum_k (D K_k) K_k (X^i) dt,
    dI^i = dY_k - (h(X^i) + h_hat) / 2 dt,

where the last term is the Ito-Stratonovich correction the gain computes (``gains.base``); the
gain is evaluated at X_{t_k}, where increment k was generated (``simulate_sde``). An increment
with NaN is missing: the particles only follow the model. ``stratonovich=False`` drops the
correction (an inconsistent scheme for a state-dependent gain, kept for comparison).
"""

from __future__ import annotations

from functools import partial
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np  # noqa: F401 - FPFResult.saved_steps is a NumPy array

from ot_filter.continuous.gains.base import Gain
from ot_filter.continuous.sde import SDEModel, check_time_step, diffusion_increment, sde_dimensions
from ot_filter.lib.static import functions_as_pytrees
from ot_filter.particles import (
    check_filter_arguments,
    initial_particle_state,
    saved_step_indices,
    scan_with_snapshots,
)

Array = jax.Array

__all__ = ["FPFResult", "fpf_step", "run_fpf"]


class FPFResult(NamedTuple):
    """Output of ``run_fpf`` (T increments, N particles, n state dimensions).

    Attributes:
      mean: ``[T, n]`` ensemble mean at t_1..t_T (after increments 0..k).
      variance: ``[T, n]`` unbiased ensemble variance per component.
      info: the gain's per-step diagnostics, each leaf with a leading axis T.
      observed: ``[T]`` bool, False where the increment had NaN.
      particles: ``[S, N, n]`` at ``saved_steps`` (None if S = 0).
      saved_steps: ``[S]`` NumPy int array of step indices (0-based, after that increment).
      final_particles: ``[N, n]``.
      final_state: the gain's state after the last step.
      rejected_updates: ``[T]`` int, particles whose filter update was non-finite at that step
        (they keep their propagation and skip the update; 0 in a healthy run).
    """

    mean: Array
    variance: Array
    info: Any
    observed: Array
    particles: Array | None
    saved_steps: np.ndarray
    final_particles: Array
    final_state: Any
    rejected_updates: Array


def fpf_step(
    key: Array,
    model: SDEModel,
    gain: Gain,
    state: Any,
    particles: Array,
    increment: Array,
    dt,
    stratonovich: bool = True,
) -> tuple[Array, Any, Any]:
    """One FPF step of ``particles[N, n]`` with ``increment[m]``.

    Returns (particles, state, info, rejected): ``rejected`` counts the particles whose update was
    non-finite (a gain blow-up): they skip the update rather than poison the ensemble with NaN.
    """
    gain_key, noise_key = jax.random.split(key)
    std = jnp.asarray(model.observation_noise_std, particles.dtype)
    h_values = jax.vmap(model.observation_function)(particles) / std  # whitened [N, m]
    observed = jnp.all(jnp.isfinite(increment))
    dy = jnp.where(observed, increment, 0.0) / std
    output, state, info = gain.apply(gain_key, state, particles, h_values)
    innovation = dy - 0.5 * (h_values + jnp.mean(h_values, axis=0)) * dt  # [N, m]
    update = jnp.einsum("inm,im->in", output.gain, innovation)
    if stratonovich:
        update = update + output.correction * dt
    update = jnp.where(observed, update, 0.0)
    finite = jnp.all(jnp.isfinite(update), axis=1, keepdims=True)
    update = jnp.where(finite, update, 0.0)
    b_shape = jax.eval_shape(model.diffusion, particles[0]).shape
    noise = jax.random.normal(noise_key, (particles.shape[0], b_shape[-1]), particles.dtype)
    diffusion = jax.vmap(lambda x, xi: diffusion_increment(model, x, xi))(particles, noise)
    drift = jax.vmap(model.drift)(particles)
    particles = particles + drift * dt + diffusion * jnp.sqrt(dt) + update
    return particles, state, info, jnp.sum(~finite)


def run_fpf(
    key: Array,
    model: SDEModel,
    gain: Gain,
    increments: Array,
    dt,
    num_particles: int,
    save_every: int = 0,
    initial_particles: Array | None = None,
    stratonovich: bool = True,
    progress: int = 0,
) -> FPFResult:
    """Filters the observation increments ``[T, m]`` (from ``simulate_sde``) with the FPF.

    Args:
      key: PRNG key.
      model: the ``SDEModel``.
      gain: ``constant_gain()``, ``kernel_gain(...)``, ``learned_gain(...)`` or ``function_gain(K)``.
      increments: ``[T, m]`` dY_0..dY_{T-1} on the grid of step dt (NaN rows: missing).
      dt: the time step (> 0; may be traced).
      num_particles: N >= 2 (static).
      save_every: keep the particles after every k-th step (0: none; static).
      initial_particles: optional ``[N, n]`` instead of N draws from pi_0.
      stratonovich: add the Ito-Stratonovich correction (static).
      progress: report every this many steps to ``ot_filter.progress`` listeners (0: off; static).
    """
    if not (isinstance(gain, tuple) and callable(getattr(gain, "init", None))
            and callable(getattr(gain, "apply", None))):
        raise TypeError(
            f"gain must be a Gain (e.g. ot_filter.continuous.kernel_gain()), got {type(gain).__name__}"
        )
    n, m, _ = sde_dimensions(model)
    check_time_step(dt)
    if jnp.ndim(increments) != 2 or jnp.shape(increments)[1] != m or jnp.shape(increments)[0] < 1:
        raise ValueError(
            f"increments must have shape [T >= 1, {m}] for this model, got {jnp.shape(increments)}"
        )
    num_steps = jnp.shape(increments)[0]
    num_particles, save_every, progress = check_filter_arguments(
        num_particles, save_every, num_steps, n, initial_particles, progress
    )
    result = _run_fpf(
        key, model, functions_as_pytrees(gain), jnp.asarray(increments), dt, num_particles, save_every,
        initial_particles, bool(stratonovich), progress,
    )
    return result._replace(saved_steps=saved_step_indices(save_every, num_steps))


# The gain is a traced argument: its numbers are leaves (lib.static.bind), so new values reuse
# the program and vmap over them works.
@partial(jax.jit, static_argnames=("num_particles", "save_every", "stratonovich", "progress"))
def _run_fpf(key, model, gain, increments, dt, num_particles, save_every, initial_particles, stratonovich,
             progress):
    init_key, gain_key, steps_key = jax.random.split(key, 3)
    particle_state = initial_particle_state(init_key, model.sample_initial, num_particles, initial_particles)
    particles = particle_state.particles
    increments = increments.astype(particles.dtype)
    std = jnp.asarray(model.observation_noise_std, particles.dtype)
    state = gain.init(gain_key, particles, jax.vmap(model.observation_function)(particles) / std)

    def step(carry, inputs):
        particle_state, state = carry
        step_key, increment = inputs
        particles, state, info, rejected = fpf_step(
            step_key, model, gain, state, particle_state.particles, increment, dt, stratonovich
        )
        mean = jnp.mean(particles, axis=0)
        variance = jnp.var(particles, axis=0, ddof=1)
        outputs = (mean, variance, info, jnp.all(jnp.isfinite(increment)), rejected)
        return (particle_state._replace(particles=particles), state), outputs

    keys = jax.random.split(steps_key, increments.shape[0])
    carry, outputs, saved = scan_with_snapshots(
        step, (particle_state, state), (keys, increments), save_every,
        lambda carry: carry[0].particles, progress,
    )
    mean, variance, info, observed, rejected = outputs
    return FPFResult(mean, variance, info, observed, saved, None, carry[0].particles, carry[1], rejected)
