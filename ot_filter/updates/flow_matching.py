"""The flow-matching Bayes update: a conditional transport learned by regression.

Like ``ot()``, the update learns, from the prior particles X^i and observations simulated from
them, a map of the prior particles to the posterior that works for any y; unlike it, the map is
the flow of a velocity field v(x, t, y) fitted by least squares (``transport/flow.py``), not the
solution of a max-min game. The regression has no adversary, so its training settles: on the
chapter's static example (lambda_w = 0.4, y = 1, N = 1000, W1 per coordinate to the exact
posterior over the N-sample floor, ``benchmarks/flow_matching_static.py``) one training is
1.55-1.62 times the floor at n = 10 and 20 (three training keys), where the global ``ot()`` is
2.3-4.5 times; at n = 10 in 0.31 times its seconds (one run, one core). The map is a transport,
not the optimal one (the coupling it learns from is independent), and it costs 2 ``num_steps``
network evaluations per particle to apply.

The data are ``ot()``'s: particles and observations standardised, mini-batches from the
kernel-smoothed prior with observations simulated afresh at the jittered states
(``transport/batches.py``; the independent copies are the flow's starting points X0). The
filter machinery is ``ot()``'s too: warm starts with the halving budget ``(first, floor)``, the
divergence tests (a non-finite or exploding loss, non-finite, over-spread or far-thrown
particles, an implausible observation, the innovation trend of a filter that lost track) and
the fallback to the stochastic EnKF with the step's own simulated observations, the network
restarted.

Defaults (measured on the static example, ``benchmarks/results/flow_matching/``): an MLP of three
hidden layers of width 256 (SiLU), mini-batches of 1024, Adam at 1e-3 decayed to 0 on a cosine
over each training, 400 n iterations for one update, at least 5,000 (``default_iterations``;
250 for a filter's warm-started later steps), 32 Heun steps to apply the flow, smoothing factor
1.5.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp

from ot_filter.lib.fallback import use_where
from ot_filter.lib.static import bind
from ot_filter.lib.validation import check_int, check_number, is_traced
from ot_filter.lib.weights import uniform_log_weights
from ot_filter.model import StateSpaceModel
from ot_filter.transport.batches import sample_batch
from ot_filter.transport.divergence import CHECK_ROWS
from ot_filter.transport.divergence import diverged as divergence_test
from ot_filter.transport.divergence import predictive_z as predictive_check
from ot_filter.transport.flow import FlowTraining, VelocityNetwork, init_flow, integrate_flow, train_flow
from ot_filter.transport.networks import ACTIVATIONS
from ot_filter.transport.saddle import TrainingTrace
from ot_filter.transport.standardisation import Standardisation, identity_standardisation
from ot_filter.updates.ot import (
    check_apply_arguments,
    enkf_fallback,
    fallback_gain,
    finite_or_inf,
    iteration_schedule,
    observed_simulator,
    prior_data,
    training_data,
    trend_and_budget,
)

Array = jax.Array

__all__ = ["FlowInfo", "FlowSettings", "FlowState", "FlowStructure", "FlowUpdate", "default_iterations", "flow_matching"]


class FlowSettings(NamedTuple):
    """The update's numbers (traced: ``vmap`` over them runs in one program)."""

    learning_rate: Array  # Adam's, decayed to 0 on a cosine over each training
    divergence_threshold: Array  # the smoothed loss above this times n counts as divergence
    trend_threshold: Array  # the moving average of the normalised innovation above this: lost track
    inflation: Array  # multiplicative inflation (>= 1) of the prior anomalies before the update
    prior_smoothing: Array  # c in the smoothing bandwidth


class FlowStructure(NamedTuple):
    """The update's static structure (hashable: one compiled program per structure)."""

    first_iterations: int | None  # None: ``default_iterations`` of the state dimension
    floor_iterations: int | None
    batch_size: int
    width: int
    depth: int
    activation: str
    num_steps: int  # Heun steps of the flow from t = 0 to 1
    warm_start: bool
    smoothing: bool  # prior_smoothing is traced or nonzero


class FlowState(NamedTuple):
    log_weights: Array  # [N], uniform
    training: FlowTraining  # the velocity network's parameters and Adam's moments (the warm start)
    standardisation: Standardisation  # of the last training data
    num_updates: Array  # int scalar: updates since the network was (re-)initialised
    diverged: Array  # bool: the last training diverged; the network was re-initialised
    innovation_trend: Array  # moving average of the normalised innovation (1: tracking)


class FlowInfo(NamedTuple):
    loss: Array  # [first iterations] the flow-matching loss of each iteration (+inf: not run)
    final_loss: Array  # its moving average at the end of training
    diverged: Array  # bool: training diverged; the EnKF update was used instead
    predictive_z: Array  # max over coordinates of |y - mean Y'| / std Y', Y' simulated at the
    #                      transported particles (0 for a missing observation)
    innovation_trend: Array  # moving average over updates of the normalised prior innovation


class FlowUpdate(NamedTuple):
    """``BayesUpdate``'s ``init``/``apply``, plus the trained flow:
    ``transport(state, particles[N, n], observation[m] | [N, m] | [K, m])`` moves particles
    along the flow trained by the last ``apply`` (``[m]``: the posterior for that y; ``[N, m]``:
    particle i conditioned on y_i; ``[K, m]`` with K != N: ``[K, N, n]``). After a diverged apply
    the network is re-initialised, so ``transport`` is then the identity.

    Values in ``info`` are never NaN: +inf marks a loss that was not finite."""

    init: Callable[..., FlowState]
    apply: Callable[..., tuple[Array, FlowState, FlowInfo]]
    transport: Callable[..., Array]


def default_iterations(n: int) -> tuple[int, int]:
    """``(first, floor)`` of ``flow_matching()``'s budget when not given, for state dimension n:
    400 n iterations for one update, at least 5,000, and 250 for a filter's warm-started later
    steps. Measured on the static example (``benchmarks/results/flow_matching/``, W1 per
    coordinate over the N-sample floor): at n = 10 5,000 give 1.55-1.62 and 10,000 1.46-1.49
    (three keys); at n = 20 both about 1.6; at n = 50 5,000 give 5.7-6.6 and 20,000 1.97."""
    return max(5_000, 400 * n), 250


def flow_matching(
    num_iterations: int | tuple[int, int] | None = None,
    batch_size: int = 1024,
    width: int = 256,
    depth: int = 3,
    activation: str = "silu",
    num_steps: int = 32,
    learning_rate: float = 1e-3,
    warm_start: bool = True,
    divergence_threshold: float = 10.0,
    trend_threshold: float = 10.0,
    inflation: float = 1.0,
    prior_smoothing: float = 1.5,
) -> FlowUpdate:
    """Builds the flow-matching Bayes update.

    Structure (static: one compiled program per structure):

      num_iterations: Adam steps per update; or ``(first, floor)``: ``first`` at the first
        update, halved at every update down to ``floor`` (a warm-started filter's schedule);
        None: ``default_iterations`` of the state dimension, ``(max(5000, 400 n), 250)``.
      batch_size: joint pairs (and independent starting points) per step (>= 2).
      width, depth, activation: the velocity network, an MLP of ``depth`` hidden layers
        (activation in ``transport.ACTIVATIONS``).
      num_steps: Heun steps that integrate the flow when the particles are moved.
      warm_start: start each training from the state's parameters (else re-initialise).

    Numbers (may be traced: ``vmap`` over them runs in one program):

      learning_rate: Adam's, decayed to 0 on a cosine over each training.
      divergence_threshold: the smoothed loss above this times n counts as divergence (the loss
        of the identity flow is about 2 n in standardised units).
      trend_threshold: as ``ot()``'s: the filter lost track; the update then skips training, uses
        the EnKF and restarts the network until the trend is back in range.
      inflation: multiplies the prior particles' anomalies before the update.
      prior_smoothing: c in the kernel bandwidth of the smoothed prior the flow is trained on
        (as ``ot()``'s; 0: train on the particles themselves, whose well-trained flow carries the
        particles onto the atoms of their own weighted posterior and collapses as SIR does).
    """
    # None: ``default_iterations`` of the state dimension, at apply.
    first, floor = (None, None) if num_iterations is None else iteration_schedule(num_iterations)
    if activation not in ACTIVATIONS:
        raise ValueError(f"activation must be one of {sorted(ACTIVATIONS)}, got {activation!r}")
    settings = FlowSettings(
        learning_rate=check_number("learning_rate", learning_rate, 0.0, strict_minimum=True),
        divergence_threshold=check_number("divergence_threshold", divergence_threshold, 0.0, strict_minimum=True),
        trend_threshold=check_number("trend_threshold", trend_threshold, 0.0, strict_minimum=True),
        inflation=check_number("inflation", inflation, 1.0),
        prior_smoothing=check_number("prior_smoothing", prior_smoothing, 0.0),
    )
    structure = FlowStructure(
        first_iterations=first,
        floor_iterations=floor,
        batch_size=check_int("batch_size", batch_size, minimum=2),
        width=check_int("width", width),
        depth=check_int("depth", depth),
        activation=activation,
        num_steps=check_int("num_steps", num_steps),
        warm_start=bool(warm_start),
        smoothing=is_traced(prior_smoothing) or float(prior_smoothing) > 0,
    )
    return FlowUpdate(
        init=bind(_init, settings, structure=structure),
        apply=bind(_apply_checked, settings, structure=structure),
        transport=bind(_transport_checked, structure=structure),
    )


def velocity_network(structure) -> VelocityNetwork:
    """The velocity MLP of a structure with ``width``, ``depth`` and ``activation`` (this
    update's, ``local_flow()``'s)."""
    return VelocityNetwork(structure.width, structure.depth, structure.activation)


def _init(settings: FlowSettings, key: Array, particles: Array, model: StateSpaceModel | None = None, *,
          structure: FlowStructure) -> FlowState:
    if model is None:
        raise ValueError("flow_matching().init needs the model (for the observation dimension): "
                         "init(key, particles, model)")
    if particles.ndim != 2 or particles.shape[0] < 2:
        raise ValueError(f"particles must have shape [N >= 2, n], got {particles.shape}")
    n = particles.shape[1]
    y = jax.eval_shape(model.sample_observation, key, particles[0])
    if y.ndim != 1:
        raise ValueError(f"model.sample_observation must return y[m], got shape {y.shape}")
    m, dtype = y.shape[0], particles.dtype
    return FlowState(
        log_weights=uniform_log_weights(particles),
        training=init_flow(key, velocity_network(structure), n, m, dtype),
        standardisation=identity_standardisation(n, m, dtype),
        num_updates=jnp.zeros((), jnp.int32),
        diverged=jnp.array(False),
        innovation_trend=jnp.ones((), dtype),
    )


def _apply_checked(settings: FlowSettings, key: Array, state: FlowState, particles: Array, observation: Array,
                   model: StateSpaceModel, *, structure: FlowStructure):
    """Shapes checked here; the work is one compiled program (also when called outside jit)."""
    observation = check_apply_arguments(state, particles, observation)
    return _apply(settings, key, state, particles, observation, model, structure=_sized(structure, particles.shape[1]))


def _sized(structure: FlowStructure, n: int) -> FlowStructure:
    """The structure with ``default_iterations(n)`` where the budget was not given (static: n is
    a shape)."""
    if structure.first_iterations is not None:
        return structure
    first, floor = default_iterations(n)
    return structure._replace(first_iterations=first, floor_iterations=floor)


@jax.jit(static_argnames=("structure",))
def _apply(settings, key, state, particles, observation, model, structure):
    """Simulate, standardise, train, move along the flow, check, fall back."""
    n = particles.shape[1]
    simulate_key, train_key, check_key, reset_key = jax.random.split(key, 4)
    network = velocity_network(structure)

    # 1. Training data, as ot()'s: Y^i ~ h(. | X^i), standardised over the active particles.
    prior = prior_data(settings, simulate_key, state.log_weights, particles, observation, model)
    particles, simulated, active, num_active, scaling, observed, xs, ys = prior
    m = ys.shape[1]
    sample_observation = observed_simulator(model, observed, scaling)
    data = training_data(prior, settings.prior_smoothing, structure.smoothing)

    # 2. Regression (none while the filter has lost track), warm-started unless told otherwise.
    trend, lost, budget = trend_and_budget(state, prior, observation, settings.trend_threshold,
                                           structure.first_iterations, structure.floor_iterations)
    fresh = init_flow(reset_key, network, n, m, xs.dtype)
    training = state.training if structure.warm_start else fresh
    training, trace = train_flow(
        train_key, training,
        # Fresh observations always: y simulated at the (jittered) pair, X0 an independent copy.
        lambda batch_key: sample_batch(batch_key, data, sample_observation, batch_size=structure.batch_size,
                                       smoothing=structure.smoothing, fresh_observations=True, enkf_layer=False),
        budget, network=network, learning_rate=settings.learning_rate, record_length=structure.first_iterations,
    )
    trace = TrainingTrace(trace.loss, jnp.where(budget > 0, trace.smoothed_loss, 0.0), trace.finite)

    # 3. Move the particles along the flow to the actual observation.
    y_standard = jnp.where(observed, scaling.standardise_y(observation), 0.0)
    moved = _flow(structure, training.params, xs, jnp.broadcast_to(y_standard, ys.shape))

    # 4. Divergence: loss, spread, far-thrown particles, posterior predictive, lost track.
    checked = data.active_index[:CHECK_ROWS]
    z = predictive_check(check_key, model, scaling.restore_x(moved[checked]), observation, active[checked])
    diverged = lost | divergence_test(trace.finite, trace.smoothed_loss, settings.divergence_threshold, n,
                                      moved, active, z, xs)

    # 5. Fall back where it diverged (the stochastic EnKF with this update's own simulated
    #    observations) and restart the network with the full budget.
    enkf_particles, _ = enkf_fallback(
        xs, y_standard, ys, fallback_gain(model, particles, xs, ys, scaling, observed, active),
        scaling, active, num_active)
    posterior = use_where(~diverged, scaling.restore_x(moved), enkf_particles)
    posterior = jnp.where(jnp.any(observed), posterior, particles)
    training = use_where(diverged, fresh, training)

    state = FlowState(
        log_weights=state.log_weights,
        training=training,
        standardisation=scaling,
        num_updates=jnp.where(diverged, 0, state.num_updates + 1),
        diverged=diverged,
        innovation_trend=trend,
    )
    info = FlowInfo(
        loss=trace.loss,
        final_loss=finite_or_inf(trace.smoothed_loss),
        diverged=diverged,
        predictive_z=finite_or_inf(z),
        innovation_trend=trend,
    )
    return posterior, state, info


def _flow(structure: FlowStructure, params, xs: Array, y_rows: Array) -> Array:
    network = velocity_network(structure)
    return integrate_flow(lambda x, t, y: network.apply(params, x, t, y), xs, y_rows, structure.num_steps)


def _transport_checked(state: FlowState, particles: Array, observation: Array, *, structure: FlowStructure) -> Array:
    scaling = state.standardisation
    n, m = scaling.x_mean.shape[0], scaling.y_mean.shape[0]
    if particles.ndim != 2 or particles.shape[1] != n:
        raise ValueError(f"particles must have shape [N, {n}], got {particles.shape}")
    observation = jnp.asarray(observation, particles.dtype)
    if observation.ndim not in (1, 2) or observation.shape[-1] != m:
        raise ValueError(f"observation must have shape [{m}], [N, {m}] or [K, {m}], got {observation.shape}")
    return _transport(state, particles, observation, structure=structure)


@jax.jit(static_argnames=("structure",))
def _transport(state, particles, observation, structure):
    scaling = state.standardisation
    xs, y_standard = scaling.standardise_x(particles), scaling.standardise_y(observation)

    def move(y_rows):
        rows = jnp.broadcast_to(y_rows, (particles.shape[0], y_rows.shape[-1]))
        return scaling.restore_x(_flow(structure, state.training.params, xs, rows))

    if observation.ndim == 1 or observation.shape[0] == particles.shape[0]:
        return move(y_standard)
    return jax.vmap(move)(y_standard)
