"""The localised flow-matching Bayes update: one velocity field shared by every state coordinate.

``local_ot()``'s windows, layers and local pairs (``updates/local_ot.py``) with
``flow_matching()``'s regression (``transport/flow.py``) in place of the max-min game. Each
state coordinate i sees its local window (the state coordinates W_i, itself first, and the
observations O_i within reach); ONE velocity field v(x_W, t, y_O, context), shared by all
coordinates, is fitted by least squares on local pairs,

    v = argmin E |v(x_t, t, Y_O) - (X1 - X0)|^2,   x_t = (1 - t) X0 + t X1,

with (X1, Y_O) a particle's window and its local observations at a random coordinate and X0 the
starting point of the flow: another particle's window at the same coordinate (independent of
Y_O: the flow carries the local prior to the local posterior), or with a layer that copy's local
EnKF analysis for Y_O (given Y_O independent of X1: the flow carries the layer's analysis to the
local posterior, and is the identity where the layer is already right). Coordinate i takes the
first component (itself) of its window's flow, as the LETKF keeps the centre of each local
analysis.

Where the windows hold one state coordinate (``state_radius = 0``) the flow is a flow on the line,
and the map it integrates to is increasing: the monotone rearrangement of the starting law onto
the learned local posterior, that is the one-dimensional optimal transport (and exactly the
identity where the two laws agree). The particles keep their ranks in every coordinate, so the
ensemble keeps the prior's (or the layer's) dependence between coordinates, as a localised
ensemble transform does.

Every particle gives n local pairs, so the per-iteration cost does not depend on n; the flow's
application (2 ``num_steps`` forward passes of N n windows) grows linearly. Warm starts with the
halving budget, the divergence tests and the fallback (the layer alone: the local EnKF, or the
LETKF-like deterministic layer) are ``local_ot()``'s, except that with a layer the far-thrown
test measures from the flow's start (the layer's analysis, itself the fallback) rather than
from the prior.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ot_filter.lib.fallback import use_where
from ot_filter.lib.static import bind
from ot_filter.lib.validation import check_int, check_number, is_traced
from ot_filter.lib.weights import active_first, active_mask, uniform_log_weights
from ot_filter.localisation import LocalWindows
from ot_filter.model import StateSpaceModel
from ot_filter.transport.divergence import CHECK_ROWS
from ot_filter.transport.divergence import diverged as divergence_test
from ot_filter.transport.divergence import predictive_z as predictive_check
from ot_filter.transport.flow import FlowTraining, VelocityNetwork, init_flow, integrate_flow, train_flow
from ot_filter.transport.networks import ACTIVATIONS
from ot_filter.transport.saddle import Batch, TrainingTrace, transport_input
from ot_filter.transport.standardisation import Standardisation, identity_standardisation
from ot_filter.updates.flow_matching import FlowInfo, velocity_network
from ot_filter.updates.local_ot import (
    LocalOTSettings,
    conditioning_size,
    layer_inputs,
    local_data,
    move_windows,
    window_sizes,
    local_ot,
    local_pairs,
    local_update_parts,
    sample_local_batch,
    sort_columns,
)
from ot_filter.updates.ot import OTStructure, check_apply_arguments, finite_or_inf, iteration_schedule, trend_and_budget

Array = jax.Array

__all__ = ["LocalFlowSettings", "LocalFlowState", "LocalFlowUpdate", "local_flow"]


class LocalFlowSettings(NamedTuple):
    """The numbers (traced: ``vmap`` over them runs in one program)."""

    local: LocalOTSettings  # the windows, context levels, layer taper, inflation and thresholds
    learning_rate: Array  # Adam's, decayed to 0 on a cosine over each training
    tail_particles: Array  # int k: the k least and k largest starts of a column are displaced as the (k+1)-th


class LocalFlowStructure(NamedTuple):
    """The static structure (hashable: one compiled program per structure)."""

    local: OTStructure  # the local pairs' structure (layer, fresh observations, context)
    first_iterations: int
    floor_iterations: int
    batch_size: int
    width: int
    depth: int
    activation: str
    num_steps: int
    warm_start: bool
    fresh_where_gaussian: bool  # fresh observations decided at apply: where the noise is additive Gaussian


class LocalFlowState(NamedTuple):
    log_weights: Array  # [N], uniform
    training: FlowTraining  # the shared velocity network and Adam's moments (the warm start)
    standardisation: Standardisation  # of the last training data (global, per coordinate)
    simulated_observations: Array  # [N, m] Y^i ~ h(. | X^i) of the last update (the perturbed layer's gain)
    num_updates: Array  # updates since the network was (re-)initialised
    diverged: Array
    innovation_trend: Array  # moving average of the normalised innovation (1: tracking)


class LocalFlowUpdate(NamedTuple):
    """``BayesUpdate``'s ``init``/``apply`` (``info`` is a ``FlowInfo``), plus
    ``transport(state, particles, observation[m], model=None)``: the prior particles of the last
    ``apply`` moved by its trained flow for another observation (the deterministic layer needs the
    model)."""

    init: Callable[..., LocalFlowState]
    apply: Callable[..., tuple[Array, LocalFlowState, FlowInfo]]
    transport: Callable[..., Array]


def local_flow(
    windows: LocalWindows,
    num_iterations: int | tuple[int, int] = (2_000, 500),
    batch_size: int = 512,
    width: int = 64,
    depth: int = 3,
    activation: str = "silu",
    num_steps: int = 16,
    learning_rate: float = 1e-3,
    enkf_layer: bool | str = False,
    taper: str = "step",
    warm_start: bool = True,
    divergence_threshold: float = 10.0,
    trend_threshold: float = 10.0,
    inflation: float = 1.0,
    prior_context: int = 8,
    location_context: bool = False,
    fresh_observations: bool | None = None,
    tail_particles: int = 2,
) -> LocalFlowUpdate:
    """Builds the localised flow-matching update.

    Args:
      windows: ``localisation.local_windows(model.geometry, radius, state_radius)``.
      num_iterations: Adam steps per update, or ``(first, floor)``: ``first`` at the first
        update, halved at every update down to ``floor`` (warm starts).
      batch_size: local pairs per step; width, depth, activation: the shared velocity MLP.
      num_steps: Heun steps of the flow.
      learning_rate: Adam's, decayed to 0 on a cosine over each training (traced allowed).
      tail_particles: k: the k least and k largest starts of each window coordinate (active
        particles) are displaced as the (k+1)-th, the next one in, is (``_tail_safe_flow``; 0: the flow everywhere).
      fresh_observations: draw each mini-batch's local observations afresh (``local_ot()``'s
        option); None (default): wherever the model has additive Gaussian observation noise
        (``model.observation_function`` and ``observation_noise_cov``). With the simulated ones
        alone, the regression fits each pair's one noise draw: on a linear-Gaussian case with the
        deterministic layer (12 coordinates, N = 100, three seeds) the flow then moved the LETKF's
        exact analysis by 0.11-0.18 posterior spreads on average, and by 0.06-0.08 with fresh
        observations (``local_ot()``: 0.22-0.41).
      enkf_layer, taper, prior_context, location_context, inflation, divergence_threshold,
        trend_threshold: ``local_ot()``'s (the layer is the flow's starting point; the
        deterministic layer needs a model with additive Gaussian observation noise).
    """
    first, floor = iteration_schedule(num_iterations)
    if activation not in ACTIVATIONS:
        raise ValueError(f"activation must be one of {sorted(ACTIVATIONS)}, got {activation!r}")
    # local_ot() validates and holds the windows, the layer and the local pairs' settings (its
    # saddle-point settings are built and unused: one place validates the shared arguments).
    pairs = local_ot(windows, num_iterations=first, enkf_layer=enkf_layer, taper=taper,
                     divergence_threshold=divergence_threshold, trend_threshold=trend_threshold,
                     inflation=inflation, prior_context=prior_context, location_context=location_context,
                     fresh_observations=bool(fresh_observations))
    local_numbers, local_structure = local_update_parts(pairs)
    settings = LocalFlowSettings(local_numbers,
                                 check_number("learning_rate", learning_rate, 0.0, strict_minimum=True),
                                 jnp.asarray(check_int("tail_particles", tail_particles, minimum=0), jnp.int32))
    structure = LocalFlowStructure(
        local=local_structure, first_iterations=first, floor_iterations=floor,
        batch_size=check_int("batch_size", batch_size, minimum=2), width=check_int("width", width),
        depth=check_int("depth", depth), activation=activation, num_steps=check_int("num_steps", num_steps),
        warm_start=bool(warm_start), fresh_where_gaussian=fresh_observations is None,
    )
    return LocalFlowUpdate(init=bind(_init, settings, structure=structure),
                           apply=bind(_apply_checked, settings, structure=structure),
                           transport=bind(_transport_checked, settings, structure=structure))


def _init(settings: LocalFlowSettings, key: Array, particles: Array, model: StateSpaceModel | None = None, *,
          structure: LocalFlowStructure) -> LocalFlowState:
    if model is None:
        raise ValueError("local_flow().init needs the model (for the observation dimension): "
                         "init(key, particles, model)")
    n, window, _ = window_sizes(settings.local.windows)
    if particles.ndim != 2 or particles.shape[0] < 2 or particles.shape[1] != n:
        raise ValueError(f"particles must have shape [N >= 2, {n}] (the windows' n), got {particles.shape}")
    m = jax.eval_shape(model.sample_observation, key, particles[0]).shape[0]
    observations = settings.local.windows.observations
    if not is_traced(observations) and int(np.max(np.asarray(observations))) >= m:
        raise ValueError(f"the windows index observations beyond the model's m = {m}: "
                         "build them from this model's geometry")
    dtype = particles.dtype
    conditioning = conditioning_size(settings.local, structure.local)
    return LocalFlowState(
        log_weights=uniform_log_weights(particles),
        training=init_flow(key, velocity_network(structure), window, conditioning, dtype),
        standardisation=identity_standardisation(n, m, dtype),
        simulated_observations=jnp.zeros((particles.shape[0], m), dtype),
        num_updates=jnp.zeros((), jnp.int32),
        diverged=jnp.array(False),
        innovation_trend=jnp.ones((), dtype),
    )


def _apply_checked(settings: LocalFlowSettings, key: Array, state: LocalFlowState, particles: Array,
                   observation: Array, model: StateSpaceModel, *, structure: LocalFlowStructure):
    observation = check_apply_arguments(state, particles, observation)
    if structure.fresh_where_gaussian:  # static: whether the model gives h and R
        local = structure.local._replace(fresh_observations=model.has_gaussian_observation_noise)
        structure = structure._replace(local=local, fresh_where_gaussian=False)
    return _apply(settings, key, state, particles, observation, model, structure=structure)


@jax.jit(static_argnames=("structure",))
def _apply(settings, key, state, particles, observation, model, structure):
    """Simulate, standardise, cut windows, fit the shared velocity, move, check, fall back."""
    numbers, local = settings.local, structure.local
    _, window, slots = window_sizes(numbers.windows)
    conditioning = conditioning_size(numbers, local)
    simulate_key, train_key, check_key, reset_key = jax.random.split(key, 4)
    network = velocity_network(structure)

    prior, data = local_pairs(numbers, local, simulate_key, state.log_weights, particles, observation, model)
    particles, simulated, active, num_active, scaling, observed, xs, ys = prior
    active_index = active_first(active)

    def sample_batch(batch_key):
        # X1, Y: the pair; X0: the copy, through the layer at the pair's Y where there is one.
        batch = sample_local_batch(batch_key, local, data, active_index, num_active, structure.batch_size)
        return Batch(batch.x, batch.y, transport_input(batch.xbar, batch.y, batch.ybar, batch.gain), batch.ybar)

    trend, lost, budget = trend_and_budget(state, prior, observation, numbers.ot.trend_threshold,
                                           structure.first_iterations, structure.floor_iterations)
    fresh = init_flow(reset_key, network, window, conditioning, xs.dtype)
    training = state.training if structure.warm_start else fresh
    training, trace = train_flow(train_key, training, sample_batch, budget, network=network,
                                 learning_rate=settings.learning_rate, record_length=structure.first_iterations)
    trace = TrainingTrace(trace.loss, jnp.where(budget > 0, trace.smoothed_loss, 0.0), trace.finite)

    moved = move_windows(data, _tail_safe_flow(network, training.params, structure.num_steps, active, settings.tail_particles),
                  local.enkf_layer, slots, 0, active)

    checked = active_index[:min(CHECK_ROWS, particles.shape[0])]
    z = predictive_check(check_key, model, scaling.restore_x(moved[checked]), observation, active[checked])
    # Far-thrown particles are judged from the flow's starts (the layer's analysis: the fallback
    # itself), so that the layer's own moves do not count against the flow.
    start = move_windows(data, None, True, slots)
    diverged = lost | divergence_test(trace.finite, trace.smoothed_loss, numbers.ot.divergence_threshold,
                                      window, moved, active, z, start if local.enkf_layer else xs)
    posterior = use_where(~diverged, scaling.restore_x(moved), scaling.restore_x(start))
    posterior = jnp.where(jnp.any(observed), posterior, particles)
    training = use_where(diverged, fresh, training)

    state = LocalFlowState(
        log_weights=state.log_weights,
        training=training,
        standardisation=scaling,
        simulated_observations=simulated,
        num_updates=jnp.where(diverged, 0, state.num_updates + 1),
        diverged=diverged,
        innovation_trend=trend,
    )
    info = FlowInfo(loss=trace.loss, final_loss=finite_or_inf(trace.smoothed_loss), diverged=diverged,
                    predictive_z=finite_or_inf(z), innovation_trend=trend)
    return posterior, state, info


def _tail_safe_flow(network: VelocityNetwork, params, num_steps: int, active: Array, tail: Array) -> Callable:
    """``transport(x[N, S], y[N, C])`` for ``move_windows``: the flow from each start, except that the
    ``tail`` least and largest starts of each column (active rows) are displaced as the next one
    in is (translated with it). Why: the shared field is fitted where the starts are dense, and a particle in the far tail
    of one window (one start in a hundred) is where it extrapolates; on Lorenz-96 with y = x^2 the
    unclipped flow threw such particles up to 3.5 prior standard deviations beyond the LETKF's analysis
    of them, and the outliers persisted from step to step. A translation keeps the layer's tails."""
    def transport(x, y):
        ordered = sort_columns(jnp.where(active[:, None], x, jnp.inf))
        last = jnp.maximum(jnp.sum(active, dtype=jnp.int32) - 1, 0)
        count = jnp.minimum(tail, last // 2)  # bounds in order however few particles are active
        low, high = ordered[count], ordered[last - count]
        inner = jnp.clip(x, low, high)
        return x + integrate_flow(lambda u, t, c: network.apply(params, u, t, c), inner, y, num_steps) - inner

    return transport


def _transport_checked(settings: LocalFlowSettings, state: LocalFlowState, particles: Array, observation: Array,
                       model: StateSpaceModel | None = None, *, structure: LocalFlowStructure) -> Array:
    if structure.local.deterministic_layer and model is None:
        raise ValueError("the deterministic layer's transport needs the model: transport(state, particles, "
                         "observation, model)")
    num, m = state.simulated_observations.shape
    n = state.standardisation.x_mean.shape[0]
    if jnp.shape(particles) != (num, n) or jnp.shape(observation) != (m,):
        raise ValueError(f"particles must have shape ({num}, {n}) and observation ({m},), got "
                         f"{jnp.shape(particles)} and {jnp.shape(observation)}")
    return _transport(settings, state, particles, jnp.asarray(observation, particles.dtype), model,
                      structure=structure)


@jax.jit(static_argnames=("structure",))
def _transport(settings, state, particles, observation, model, structure):
    numbers, local = settings.local, structure.local
    scaling = state.standardisation
    observed = jnp.isfinite(observation)
    active = active_mask(state.log_weights)
    data = local_data(numbers, scaling.standardise_x(particles),
                       jnp.where(observed, scaling.standardise_y(state.simulated_observations), 0.0),
                       jnp.where(observed, scaling.standardise_y(observation), 0.0), observed, active,
                       layer_inputs(local, model, particles, scaling), scaling if local.location_context else None)
    flow = _tail_safe_flow(velocity_network(structure), state.training.params, structure.num_steps, active,
                           settings.tail_particles)
    return scaling.restore_x(move_windows(data, flow, local.enkf_layer, window_sizes(numbers.windows)[2], 0, active))
