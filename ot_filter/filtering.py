"""Whole-trajectory particle filters: one ``lax.scan`` of propagate-then-update.

    X^i_0 ~ pi_0;   for t = 1..T:   X^i_t <- a(. | X^i_{t-1})  (propagation, model simulator)
                                    X_t   <- update.apply(key, state, X_t, y_t, model)  (Bayes)

(the chapter's eq. exact-posterior with both operators replaced by particle approximations).

The result holds the filtering mean and spread after each observation (weighted for SIR), the
stacked per-step ``info`` of the update, and the particles at every k-th step or none, so that
memory stays bounded for long runs with many particles. The whole filter is one jit-compiled
program; it can itself be jitted and vmapped over keys and observation sequences.

Missing observations: NaN components of y_t are missing and the update assimilates the others
(the same result as deleting those rows of the observation model: ``updates.base``); the set of
observed components may change at every step without recompiling (it is a mask). A time step
with every component NaN is skipped (the update is the identity, ``observed[t]`` is False and
that step's ``info`` is zeros); propagation goes on.

Padded particle axis: ``num_active = k`` runs the filter with k particles inside arrays of
``num_particles = N_max`` (the contract in ``updates.base``: after ``update.init`` the
log-weights are -log k on the first k particles and -inf, padding, on the rest). k is a traced
argument, so one compiled program serves every k and ``jax.vmap`` runs a whole particle-count
sweep at once; the filter mean and spread are over the active particles only. Since
``jax.random`` streams are prefix-consistent (``jax_threefry_partitionable``, the default), the
first k initial draws and propagation noises are those of an unpadded run with N = k and the same
key: the EnKF without rotation then reproduces that run up to floating-point rounding.
"""

from __future__ import annotations

from functools import partial
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ot_filter.metrics import spread as ensemble_spread
from ot_filter.model import StateSpaceModel, model_dimensions, with_observation_noise_factors
from ot_filter.particles import (
    ParticleState,
    check_filter_arguments,
    check_num_active,
    initial_particle_state,
    saved_step_indices,
    scan_with_snapshots,
)
from ot_filter.lib.static import functions_as_pytrees
from ot_filter.updates.base import BayesUpdate

Array = jax.Array

__all__ = ["FilterResult", "run_filter"]


class FilterResult(NamedTuple):
    """Output of ``run_filter`` (T observation times, N particles, n state dimensions).

    Attributes:
      mean: ``[T, n]`` filtering mean after each update (weighted by the particle weights; over
        the active particles only with ``num_active``).
      spread: ``[T]`` ensemble spread (``metrics.spread``: sqrt of the mean over components of the
        unbiased weighted variance, as DAPPER's; padding has weight 0).
      info: the update's per-step diagnostics, each leaf with a leading axis T.
      observed: ``[T]`` bool, False where every component was NaN and the update was skipped.
      particles: ``[S, N, n]`` particles after the updates at ``saved_steps`` (None if S = 0).
      log_weights: ``[S, N]`` their normalised log-weights (None if S = 0).
      saved_steps: ``[S]`` NumPy int array, the time indices (0-based) of the saved particles.
      final_particles: ``[N, n]`` particles after the last step (to continue filtering).
      final_state: the update's state after the last step.
    """

    mean: Array
    spread: Array
    info: Any
    observed: Array
    particles: Array | None
    log_weights: Array | None
    saved_steps: np.ndarray
    final_particles: Array
    final_state: Any


def run_filter(
    key: Array,
    model: StateSpaceModel,
    update: BayesUpdate,
    observations: Array,
    num_particles: int,
    save_every: int = 1,
    initial_particles: Array | None = None,
    num_active: Array | int | None = None,
    update_first: bool = False,
    progress: int = 0,
    particle_sharding: jax.sharding.NamedSharding | None = None,
) -> FilterResult:
    """Filters a sequence of observations with a particle Bayes update.

    Args:
      key: PRNG key.
      model: the state-space model (its simulator propagates the particles).
      update: a ``BayesUpdate`` (``ot_filter.sir(...)``, ``ot_filter.enkf(...)``, ``ot_filter.ot(...)``);
        a traced argument: its numeric settings may be traced (``jax.vmap`` over
        ``enkf(inflation=a)`` runs in one program; a new value does not recompile).
      observations: ``[T, m]`` observations y_1..y_T (NaN components are missing; a row of NaN
        skips that step's update).
      num_particles: N >= 2 (static).
      save_every: keep the particles of every k-th step (steps k-1, 2k-1, ...); 1 keeps all,
        0 keeps none, as does any k > T (static).
      initial_particles: optional finite ``[N, n]`` initial ensemble instead of N draws from pi_0
        (e.g. a filter started from a different prior than the truth).
      num_active: optional number k of active particles, 2 <= k <= N, an int or a traced int
        scalar (it may be vmapped over); the other N - k are padding (see the module docstring).
        None: all N are active. A Python or concrete value out of range raises ValueError; a
        traced one out of range gives NaN ``mean`` and ``spread``.
      update_first: assimilate y_t at the current particles, then propagate (static). This is
        the order of a discretised continuous-time model (``continuous.discretise``), whose
        increment dY_k is generated at X_{t_k}; ``mean`` and the saved particles are then those
        of the predictive distribution at t_{k+1} given dY_0..dY_k, i.e. the continuous-time
        filter at t_{k+1}.
      progress: report every this many steps to ``ot_filter.progress`` listeners (0: off, no
        callback compiled in; static).
      particle_sharding: split the particles over devices, e.g.
        ``ot_filter.particle_sharding()`` (N divisible by the device count; static). Same key,
        same result as on one device up to the rounding of cross-device sums (``sharding.py``).

    Returns:
      A ``FilterResult``.
    """
    if not (isinstance(update, tuple) and callable(getattr(update, "init", None))
            and callable(getattr(update, "apply", None))):
        raise TypeError(
            f"update must be a BayesUpdate or another NamedTuple with init and apply (e.g. "
            f"ot_filter.sir()), got {type(update).__name__}"
        )
    state_dim, observation_dim = model_dimensions(model)
    if jnp.ndim(observations) != 2 or jnp.shape(observations)[1] != observation_dim:
        raise ValueError(
            f"observations must have shape [T, {observation_dim}] for this model, "
            f"got {jnp.shape(observations)}"
        )
    num_steps = jnp.shape(observations)[0]
    if num_steps < 1:
        raise ValueError("observations must hold at least one time step (T >= 1)")
    num_particles, save_every, progress = check_filter_arguments(
        num_particles, save_every, num_steps, state_dim, initial_particles, progress
    )
    if num_active is not None:
        num_active = check_num_active(num_active, num_particles)
    if particle_sharding is not None:
        devices = particle_sharding.mesh.size
        if not isinstance(particle_sharding, jax.sharding.NamedSharding):
            raise TypeError("particle_sharding must be a NamedSharding, e.g. ot_filter.particle_sharding()")
        if num_particles % devices:
            raise ValueError(
                f"num_particles = {num_particles} must be divisible by the {devices} devices of "
                f"particle_sharding"
            )
    result = _run_filter(
        key, model, functions_as_pytrees(update), jnp.asarray(observations), num_particles, save_every,
        initial_particles, num_active, bool(update_first), progress, particle_sharding,
    )
    return result._replace(saved_steps=saved_step_indices(save_every, num_steps))


# The update is a traced argument: built-in updates are pytrees whose leaves are their numbers
# (lib.static.bind), so new values reuse the program and vmap over them works.
@partial(jax.jit, static_argnames=("num_particles", "save_every", "update_first", "progress",
                                   "particle_sharding"))
def _run_filter(
    key, model, update, observations, num_particles, save_every, initial_particles, num_active,
    update_first, progress, particle_sharding,
):
    if particle_sharding is None:
        return _filter_body(key, model, update, observations, num_particles, save_every,
                            initial_particles, num_active, update_first, progress, lambda x: x)
    with jax.sharding.use_abstract_mesh(particle_sharding.mesh.abstract_mesh):  # for sharding.replicated
        return _filter_body(
            key, model, update, observations, num_particles, save_every, initial_particles,
            num_active, update_first, progress,
            lambda x: jax.lax.with_sharding_constraint(x, particle_sharding),
        )


def _filter_body(
    key, model, update, observations, num_particles, save_every, initial_particles, num_active,
    update_first, progress, place,
):
    """The filter's trace; ``place`` lays a particle array ``[N, ...]`` out on the devices."""
    init_key, state_key, steps_key = jax.random.split(key, 3)
    if num_active is not None:
        # A traced count out of range cannot raise: it is clipped for the run, and its mean and
        # spread are NaN.
        valid = (num_active >= 2) & (num_active <= num_particles)
        num_active = jnp.clip(num_active, 2, num_particles)
    particle_state = initial_particle_state(
        init_key, model.sample_initial, num_particles, initial_particles, num_active
    )
    particles = place(particle_state.particles)
    observations = observations.astype(particles.dtype)
    model = with_observation_noise_factors(model, particles.dtype)  # R factored once, not per step
    state = update.init(state_key, particles, model)
    check_update_state(state, num_particles)
    if num_active is not None:
        state = state._replace(log_weights=particle_state.log_weights)

    def step(carry, inputs):
        particle_state, state = carry
        particles = particle_state.particles
        (propagate_key, update_key), observation = inputs

        def propagate(particles):
            return jax.vmap(model.sample_transition)(
                jax.random.split(propagate_key, num_particles), particles
            )

        if not update_first:
            particles = propagate(particles)
        # NaN components are missing: the update assimilates the others (the contract in
        # updates.base); a step with nothing observed is skipped.
        observed = jnp.any(jnp.isfinite(observation))

        def skip(update_key, state, particles, observation):
            info_shape = jax.eval_shape(update.apply, update_key, state, particles, observation, model)[2]
            info = jax.tree.map(lambda leaf: jnp.zeros(leaf.shape, leaf.dtype), info_shape)
            return particles, state, info

        particles, state, info = jax.lax.cond(
            observed,
            lambda *args: update.apply(*args, model),
            skip,
            update_key, state, particles, observation,
        )
        if update_first:
            particles = propagate(particles)
        particle_state = ParticleState(place(particles), state.log_weights)
        mean = jnp.exp(particle_state.log_weights) @ particle_state.particles
        spread = ensemble_spread(particle_state.particles, particle_state.log_weights)
        return (particle_state, state), (mean, spread, info, observed)

    step_keys = jax.random.split(steps_key, observations.shape[0])
    # Each step's (propagate, update) keys, split here for all steps at once: the same keys as a
    # split inside the step, but one vectorised Threefry call instead of one per step (on CPU
    # JAX lowers Threefry to a rolled loop, whose per-op overhead is large in small steps).
    split_keys = jax.vmap(jax.random.split)(step_keys)  # [T, 2]
    step_keys = (split_keys[:, 0], split_keys[:, 1])
    carry, outputs, saved = scan_with_snapshots(
        step, (ParticleState(particles, state.log_weights), state), (step_keys, observations),
        save_every, lambda carry: carry[0], progress,
    )
    saved_particles, saved_log_weights = saved if saved is not None else (None, None)
    mean, spread, info, observed = outputs
    if num_active is not None:
        mean = jnp.where(valid, mean, jnp.nan)
        spread = jnp.where(valid, spread, jnp.nan)
    return FilterResult(
        mean=mean,
        spread=spread,
        info=info,
        observed=observed,
        particles=saved_particles,
        log_weights=saved_log_weights,
        saved_steps=None,  # filled in outside jit (a static NumPy array)
        final_particles=carry[0].particles,
        final_state=carry[1],
    )


def check_update_state(state, num_particles: int) -> None:
    """The update contract (``updates.base``): every state carries ``log_weights[N]``."""
    log_weights = getattr(state, "log_weights", None)
    if log_weights is None or not hasattr(state, "_replace") or jnp.shape(log_weights) != (num_particles,):
        raise TypeError(
            f"update.init must return a NamedTuple state with a log_weights field of shape "
            f"({num_particles},) (the contract in ot_filter.updates.base), got {type(state).__name__}"
        )
