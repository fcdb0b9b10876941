"""Whole-trajectory particle filters: one ``lax.scan`` of propagate-then-update.

    X^i_0 ~ pi_0;   for t = 1..T:   X^i_t <- a(. | X^i_{t-1})  (propagation, model simulator)
                                    X_t   <- update.apply(key, state, X_t, y_t, model)  (Bayes)

(the chapter's eq. exact-posterior with both operators replaced by particle approximations).

The result holds the filtering mean and spread after each observation (weighted for SIR), the
stacked per-step ``info`` of the update, and the particles at every k-th step or none, so that
memory stays bounded for long runs with many particles. The whole filter is one jit-compiled
program; it can itself be jitted and vmapped over keys and observation sequences.

Missing observations: a time step whose observation contains NaN is skipped (the update is the
identity, ``observed[t]`` is False and that step's ``info`` is zeros); propagation goes on.

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
from ot_filter.updates.base import BayesUpdate, uniform_log_weights
from ot_filter.progress import maybe_report

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
      observed: ``[T]`` bool, False where the observation had NaN and the update was skipped.
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
      update: a ``BayesUpdate`` (``ot_filter.sir(...)``, ``ot_filter.enkf(...)``, ``ot_filter.ot(...)``).
      observations: ``[T, m]`` observations y_1..y_T (rows with NaN are treated as missing).
      num_particles: N >= 2 (static).
      save_every: keep the particles of every k-th step (steps k-1, 2k-1, ...); 1 keeps all,
        0 keeps none, as does any k > T (static).
      initial_particles: optional ``[N, n]`` initial ensemble instead of N draws from pi_0
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
    if isinstance(num_particles, bool) or not isinstance(num_particles, (int, np.integer)):
        raise TypeError(f"num_particles must be an int, got {type(num_particles).__name__}")
    if num_particles < 2:
        raise ValueError(f"num_particles must be >= 2, got {num_particles}")
    if isinstance(save_every, bool) or not isinstance(save_every, (int, np.integer)) or save_every < 0:
        raise ValueError(f"save_every must be an int >= 0, got {save_every!r}")
    state_dim, observation_dim = model_dimensions(model)
    if jnp.ndim(observations) != 2 or jnp.shape(observations)[1] != observation_dim:
        raise ValueError(
            f"observations must have shape [T, {observation_dim}] for this model, "
            f"got {jnp.shape(observations)}"
        )
    if jnp.shape(observations)[0] < 1:
        raise ValueError("observations must hold at least one time step (T >= 1)")
    if initial_particles is not None:
        expected = (int(num_particles), state_dim)
        if jnp.shape(initial_particles) != expected:
            raise ValueError(
                f"initial_particles must have shape {expected}, got {jnp.shape(initial_particles)}"
            )
    if num_active is not None:
        num_active = _check_num_active(num_active, int(num_particles))
    num_steps = jnp.shape(observations)[0]
    if save_every > num_steps:
        save_every = 0  # no step would be saved
    progress = check_progress(progress)
    if particle_sharding is not None:
        devices = particle_sharding.mesh.size
        if not isinstance(particle_sharding, jax.sharding.NamedSharding):
            raise TypeError("particle_sharding must be a NamedSharding, e.g. ot_filter.particle_sharding()")
        if int(num_particles) % devices:
            raise ValueError(
                f"num_particles = {num_particles} must be divisible by the {devices} devices of "
                f"particle_sharding"
            )
    result = _run_filter(
        key, model, update, jnp.asarray(observations), int(num_particles), int(save_every),
        initial_particles, num_active, bool(update_first), progress, particle_sharding,
    )
    saved_steps = np.arange(save_every - 1, num_steps, save_every) if save_every else np.zeros(0, int)
    return result._replace(saved_steps=saved_steps)


def check_progress(progress) -> int:
    if isinstance(progress, bool) or not isinstance(progress, (int, np.integer)) or progress < 0:
        raise ValueError(f"progress must be an int >= 0 (report every k steps; 0: off), got {progress!r}")
    return int(progress)


def _check_num_active(num_active, num_particles: int) -> Array:
    """An int32 scalar; concrete values must lie in [2, num_particles]."""
    dtype = getattr(num_active, "dtype", None)
    if isinstance(num_active, bool) or not (
        isinstance(num_active, (int, np.integer))
        or (dtype is not None and jnp.issubdtype(dtype, jnp.integer) and jnp.ndim(num_active) == 0)
    ):
        raise TypeError(
            f"num_active must be an int or an int scalar array, got {num_active!r}"
        )
    if not isinstance(num_active, jax.core.Tracer):
        value = int(num_active)
        if not 2 <= value <= num_particles:
            raise ValueError(
                f"num_active must satisfy 2 <= num_active <= num_particles = {num_particles}, "
                f"got {value}"
            )
    return jnp.asarray(num_active, jnp.int32)


@partial(jax.jit, static_argnames=("update", "num_particles", "save_every", "update_first", "progress",
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
    if initial_particles is None:
        particles = jax.vmap(model.sample_initial)(jax.random.split(init_key, num_particles))
    else:
        particles = jnp.asarray(initial_particles)
    particles = place(particles)
    observations = observations.astype(particles.dtype)
    model = with_observation_noise_factors(model, particles.dtype)  # R factored once, not per step
    state = update.init(state_key, particles, model)
    if num_active is not None:
        # A traced count out of range cannot raise: it is clipped for the run, and its mean and
        # spread are NaN.
        valid = (num_active >= 2) & (num_active <= num_particles)
        num_active = jnp.clip(num_active, 2, num_particles)
        state = state._replace(log_weights=uniform_log_weights(particles, num_active))

    def step(carry, inputs):
        particles, state = carry
        step_key, observation = inputs
        propagate_key, update_key = jax.random.split(step_key)

        def propagate(particles):
            return jax.vmap(model.sample_transition)(
                jax.random.split(propagate_key, num_particles), particles
            )

        if not update_first:
            particles = propagate(particles)
        observed = jnp.all(jnp.isfinite(observation))
        safe_observation = jnp.where(observed, observation, jnp.zeros_like(observation))

        def skip(update_key, state, particles, observation):
            info_shape = jax.eval_shape(update.apply, update_key, state, particles, observation, model)[2]
            info = jax.tree.map(lambda leaf: jnp.zeros(leaf.shape, leaf.dtype), info_shape)
            return particles, state, info

        particles, state, info = jax.lax.cond(
            observed,
            lambda *args: update.apply(*args, model),
            skip,
            update_key, state, particles, safe_observation,
        )
        if update_first:
            particles = propagate(particles)
        particles = place(particles)
        mean = jnp.exp(state.log_weights) @ particles
        spread = ensemble_spread(particles, state.log_weights)
        return (particles, state), (mean, spread, info, observed)

    step_keys = jax.random.split(steps_key, observations.shape[0])
    carry, outputs, saved = scan_with_snapshots(
        step, (particles, state), (step_keys, observations), save_every,
        lambda carry: (carry[0], carry[1].log_weights), progress,
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
        final_particles=carry[0],
        final_state=carry[1],
    )


def scan_with_snapshots(step, carry, inputs, save_every: int, snapshot, progress: int = 0):
    """``lax.scan(step, carry, inputs)`` that also returns ``snapshot(carry)`` after every
    ``save_every``-th step (stacked; None when ``save_every`` is 0) without storing the others.

    An outer scan over blocks of ``save_every`` steps saves the snapshot at each block's end; a
    short remainder scan finishes the trajectory. ``progress`` > 0 reports every that many steps
    to ``ot_filter.progress`` listeners (static). Returns ``(carry, outputs, snapshots)``.
    """
    if progress:
        num_steps = jax.tree.leaves(inputs)[0].shape[0]
        plain_step = step

        def step(carry, indexed):  # noqa: F811 - the same step, reporting its index
            index, step_inputs = indexed
            carry, outputs = plain_step(carry, step_inputs)
            maybe_report(index, num_steps, progress)
            return carry, outputs

        inputs = (jnp.arange(num_steps), inputs)
    if save_every == 0:
        carry, outputs = jax.lax.scan(step, carry, inputs)
        return carry, outputs, None
    num_steps = jax.tree.leaves(inputs)[0].shape[0]
    num_blocks = num_steps // save_every
    blocked = num_blocks * save_every

    def block(carry, block_inputs):
        carry, outputs = jax.lax.scan(step, carry, block_inputs)
        return carry, (outputs, snapshot(carry))

    def to_blocks(array):
        return array[:blocked].reshape(num_blocks, save_every, *array.shape[1:])

    carry, (outputs, snapshots) = jax.lax.scan(block, carry, jax.tree.map(to_blocks, inputs))
    outputs = jax.tree.map(lambda a: a.reshape(blocked, *a.shape[2:]), outputs)
    if blocked < num_steps:
        carry, tail = jax.lax.scan(step, carry, jax.tree.map(lambda a: a[blocked:], inputs))
        outputs = jax.tree.map(lambda a, b: jnp.concatenate([a, b]), outputs, tail)
    return carry, outputs, snapshots
