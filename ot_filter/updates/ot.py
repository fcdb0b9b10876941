"""The optimal-transport (OT) Bayes update: the chapter's conditional transport map.

Given prior particles X^i and observations simulated from them, Y^i ~ h(. | X^i), the update
learns a map T(x, y) with (T(Xbar, Y), Y) ~ P_XY for Xbar an independent copy of X, by the
max-min problem of ``transport/saddle.py``; then X^i <- T(X^i, y) for the actual observation y.
The map is conditional: once trained it moves the same prior particles to the posterior for ANY
y (``update.transport(state, particles, y)``), without retraining. Only the simulator
``model.sample_observation`` is needed (no likelihood).

Everything is standardised first (per coordinate, particles and simulated observations), so the
defaults do not depend on the problem's scale; the map is trained and applied in standardised
coordinates and mapped back. Training starts from the parameters in the state (warm start across
filter steps) unless ``warm_start=False``.

Diagnostics (``OTInfo``): the loss curve, a divergence test and the c-concavity check.
Divergence (``transport/divergence.py``: a non-finite or exploding loss, non-finite or
over-spread transported particles, an implausible observation under the transported ensemble,
or a filter that has lost track, seen in the trend of its innovations over updates) is reported
in ``info.diverged``. That step then falls back to the stochastic (perturbed-observation) EnKF
update made with the step's own simulated observations (no second simulation; the gain
``enkf()``'s, Cov(X, h) (Cov(h) + R)^{-1}, when the noise is Gaussian with known R, else from the
simulated pairs) and the networks are re-initialised with the iteration schedule restarted, so
that a filter never carries garbage forward. The predictive test, and the J of a map used without
training, read the first ``CHECK_ROWS`` active particles (``transport/divergence.py``).

Small particle counts: trained on the N pairs alone, the networks resolve individual pairs and
the map learns the posterior of an under-smoothed prior (at N = 100 the mode masses of the static
example drift to 0.6-0.9). By default each mini-batch is therefore drawn from a kernel-smoothed
prior (``transport/standardisation.py``) with observations simulated afresh at the jittered
states (``transport/batches.py``). The map is
applied to the original particles. On the static example this halves the W1 error at N = 100 and
does not hurt N = 1000 (benchmarks/static_example.py; also checked on a bimodal prior). The
factor 1.5 on Silverman's bandwidth (since 0.2.7; it was 1) gave a lower mean W1 than 1 in all
seven comparisons made on the same seeds or truths (``benchmarks/results/ot_dimension_size_rule/``).
Static example, W1 per coordinate: n = 2, N = 1000: 0.075 -> 0.069 (3 seeds); N = 100: 0.185 ->
0.165 (lambda_w = 0.04) and 0.148 -> 0.133 (0.4; 7 of 8 seeds held both modes, 8 with 1); n = 10:
0.099 -> 0.093 (2 seeds; 1.6 gave 0.102 there, within the training's spread) and 0.139 -> 0.107
(2 other prior samples). The dynamic example's filter (forecasts not Gaussian, 10 simulations):
n = 2 0.117 -> 0.115, n = 10 0.295 -> 0.282, both within a paired standard error. The factor 2
was worse than 1.5 on that filter at n = 2 (0.125) and at N = 100 (0.168 and 0.148).

Defaults (measured on the chapter's static example): ReLU, one residual block, width and
mini-batch from the state dimension (``default_sizes``: 32 and 128 at n <= 2, the chapter's; above
that up to 1024 pairs, and width 64 growing to 128 from n = 19 and 256 from n = 37), 10 T steps
per f step, Adam(1e-3) on T and AdamW(3e-4, weight decay 1) on f, 10,000 outer iterations (500 at the later, warm-started updates of a filter),
smoothing factor 1.5. The authors' 1e-3 for f diverges after 2,000-4,000 iterations (J climbs, f's
scale grows, the map collapses onto one mode); a weight-decayed f at 3e-4 is stable over the
10,000 (at n = 2 it gives W1 0.075 against 0.087 for 1e-4, the same 3 seeds; at n = 10 with
batches of 256, 0.140 against 0.143 for 1e-3).

The builder is a recipe: it validates the structure (``OTStructure``, static) and the numbers
(``OTSettings``: learning rates, weight decay, smoothing factor, thresholds; traced, so a sweep
over them vmaps into one program) and binds the module-level steps below, which assemble the
small functions of ``transport/`` (standardisation, batches, saddle training, divergence tests)
and ``lib/`` (the fallback combinator).
"""

from __future__ import annotations

import math
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import optax

from ot_filter.lib.fallback import use_where
from ot_filter.lib.ensemble import inflate, masked_mean_and_anomalies
from ot_filter.lib.static import bind
from ot_filter.lib.validation import check_int, check_number, is_traced
from ot_filter.lib.weights import active_first, active_mask, uniform_log_weights
from ot_filter.model import StateSpaceModel, dense_noise_cov, simulate_observations
from ot_filter.transport.batches import TrainingData, own_pairs, sample_batch
from ot_filter.transport.context import ContextScaling, conditioning, context_features, context_size
from ot_filter.transport.diagnostics import c_concavity_min_eigenvalue
from ot_filter.transport.divergence import diverged as divergence_test
from ot_filter.transport.divergence import innovation_trend, lost_track, wider_than_enkf
from ot_filter.transport.divergence import CHECK_ROWS
from ot_filter.transport.divergence import predictive_z as predictive_check
from ot_filter.transport.networks import ACTIVATIONS, PotentialNetwork, TransportNetwork
from ot_filter.transport.saddle import (
    SaddleParams,
    TrainingState,
    TrainingTrace,
    batch_gain,
    empty_layer,
    enkf_gain,
    fit_layer,
    known_noise_gain,
    saddle_terms,
    train_saddle,
    transport_input,
)
from ot_filter.transport.standardisation import (
    Standardisation,
    correlation_cholesky,
    identity_standardisation,
    smoothed_draw,
    smoothing_bandwidth,
    standardisation,
)

Array = jax.Array

__all__ = [
    "OTInfo",
    "OTSettings",
    "OTState",
    "OTStructure",
    "OTUpdate",
    "Standardisation",
    "correlation_cholesky",
    "enkf_fallback",
    "fallback_gain",
    "iteration_schedule",
    "observed_simulator",
    "ot",
    "smoothed_draw",
    "training_data",
    "trend_and_budget",
]


class OTSettings(NamedTuple):
    """The OT update's numbers (traced: ``vmap`` over them runs in one program)."""

    potential_learning_rate: Array  # AdamW's on f (default optimiser only)
    potential_weight_decay: Array  # AdamW's on f (default optimiser only)
    transport_learning_rate: Array  # Adam's on T (default optimiser only)
    divergence_threshold: Array  # |smoothed J| above this times n counts as divergence
    concavity_step: Array  # difference step of the c-concavity check (standardised units)
    prior_smoothing: Array  # c in the smoothing bandwidth
    trend_threshold: Array  # the moving average of the normalised innovation above this: lost track
    inflation: Array  # multiplicative inflation (>= 1) of the prior anomalies before the update
    anchor: SaddleParams | None = None  # an offline-trained map every update starts from
    #                                     (``amortised_ot``); None: warm start / random init
    context_scaling: ContextScaling | None = None  # normalises the prior's context features


class OTStructure(NamedTuple):
    """The OT update's static structure (hashable: one compiled program per structure)."""

    first_iterations: int
    floor_iterations: int
    batch_size: int | None  # None: ``default_sizes`` of the state dimension (``sized``)
    inner_steps: int
    width: int | None  # None: as batch_size
    num_blocks: int
    activation: str
    enkf_layer: bool
    warm_start: bool
    concavity_points: int
    smoothing: bool  # prior_smoothing is traced or nonzero
    fresh_observations: bool
    potential_optimizer: optax.GradientTransformation | None  # None: AdamW from the settings
    transport_optimizer: optax.GradientTransformation | None  # None: Adam from the settings
    anchored: bool = False  # every update starts from ``settings.anchor`` (and resets to it)
    restart: bool = True  # anchored: every update starts from the anchor (else only the first
    #                       and after a divergence; later ones are warm-started as ``ot()``'s)
    contextual: bool = False  # the networks also read the prior's context (``transport/context.py``)
    deterministic_layer: bool = False  # the EnKF layer is ``saddle.DeterministicLayer`` (local_ot)
    location_context: bool = False  # (local_ot) the networks read each window's location and spread
    map_knots: int = 0  # (local_ot) T tabulated at this many points per window (0: at every particle)


class OTState(NamedTuple):
    log_weights: Array  # [N], uniform
    training: TrainingState  # network parameters and optimiser states (the warm start)
    standardisation: Standardisation  # of the last training data
    gain: Any  # [n, m] EnKF-layer gain from all particles (standardised; zeros without it), or
    #            its ``saddle.DeterministicLayer``
    simulated_observations: Array  # [N, m] Y^i ~ h(. | X^i) of the last update
    num_updates: Array  # int scalar: updates since the networks were (re-)initialised
    diverged: Array  # bool: the last training diverged; the networks were re-initialised
    innovation_trend: Array  # moving average of the normalised innovation (1: tracking)
    context: Array | None = None  # [c] the last prior's normalised context (contextual maps)


class OTInfo(NamedTuple):
    loss: Array  # [max iterations] J of each outer iteration (mini-batch estimate; +inf: not run)
    final_loss: Array  # smoothed J at the end of training
    diverged: Array  # bool: training diverged; the EnKF update was used instead
    min_hessian_eigenvalue: Array  # smallest eigenvalue of Hess_x(0.5|x|^2 - f) at checked pairs
    #                                (standardised coordinates; +inf when the check is off)
    concavity_violation: Array  # fraction of checked pairs where that eigenvalue is < 0 (0 if off)
    potential_spread: Array  # std of f(X^i, Y^i) over the first CHECK_ROWS active particles:
    #                          its growth is the first sign of divergence
    predictive_z: Array  # max over coordinates of |y - mean Y'| / std Y', Y' simulated at the
    #                      transported particles (0 for a missing observation)
    innovation_trend: Array  # moving average over updates of the normalised prior innovation;
    #                          above trend_threshold the filter lost track: EnKF, no training


class OTUpdate(NamedTuple):
    """``BayesUpdate``'s ``init``/``apply``, plus the trained conditional map:

    ``transport(state, particles[N, n], observation[m] | [N, m] | [K, m], simulated=None)``
    moves the prior particles given to the last ``apply`` with the map trained there.
    ``observation[m]`` gives the posterior ``[N, n]`` for that y; ``[N, m]`` conditions particle
    i on y_i (e.g. the joint check (T(Xbar, Y), Y)); ``[K, m]`` with K != N gives ``[K, N, n]``.
    ``simulated`` replaces the Y^i of the EnKF layer (default: those of the last apply).
    After a diverged apply (``state.diverged``) the networks are re-initialised, so ``transport``
    is then the untrained map (the identity, or the EnKF layer alone), not the EnKF fallback.
    ``potential(state, x[..., n], y[..., m])`` evaluates the trained f at points given in the
    original coordinates (f itself is the potential of the standardised problem).

    Values in ``info`` are never NaN: +inf marks a loss that was not finite.
    """

    init: Callable[..., OTState]
    apply: Callable[..., tuple[Array, OTState, OTInfo]]
    transport: Callable[..., Array]
    potential: Callable[..., Array]


def ot(
    num_iterations: int | tuple[int, int] = (10_000, 500),
    batch_size: int | None = None,
    inner_steps: int = 10,
    width: int | None = None,
    num_blocks: int = 1,
    activation: str = "relu",
    enkf_layer: bool | str = False,
    potential_optimizer: optax.GradientTransformation | None = None,
    transport_optimizer: optax.GradientTransformation | None = None,
    warm_start: bool = True,
    divergence_threshold: float = 10.0,
    trend_threshold: float = 10.0,
    inflation: float = 1.0,
    concavity_points: int = 256,
    concavity_step: float = 0.1,
    prior_smoothing: float = 1.5,
    fresh_observations: bool = True,
    potential_learning_rate: float = 3e-4,
    potential_weight_decay: float = 1.0,
    transport_learning_rate: float = 1e-3,
) -> OTUpdate:
    """Builds the OT Bayes update.

    Structure (static: one compiled program per structure):

      num_iterations: outer iterations (one f step each) per update; or ``(first, floor)``: the
        authors' filter schedule, ``first`` at the first update, halved at every update down to
        ``floor`` (e.g. ``(1024, 64)``; meant for warm-started filters). The default
        ``(10_000, 500)`` gives one update its full 10,000 and a filter's warm-started later
        steps 500 each (a filter with a constant 10,000 spent 8 s a step).
      batch_size: mini-batch size (>= 2) of joint pairs and of independent copies; None: chosen
        from the state dimension at ``init`` (``default_sizes``: 128 at n <= 2, up to 1024).
      inner_steps: T optimiser steps per outer iteration.
      width, num_blocks, activation: the networks (both f and T); activation in
        ``transport.ACTIVATIONS``; width None: chosen like the batch (32 at n <= 2, 64 up to
        n = 18, 128 up to 36, then 256).
      enkf_layer: precede T by the EnKF layer: True or ``"perturbed"``, x + K (y - Y^i);
        ``"deterministic"``, m + K (y - mean Y) + A (x - m) with A the Gaussian OT map to the
        Kalman posterior covariance (no observation-perturbation noise: ``transport/saddle.py``).
      potential_optimizer: an optax transformation for f replacing the default AdamW (then the
        two ``potential_*`` numbers are unused). It is given the negated gradient: f is maximised.
      transport_optimizer: an optax transformation for T replacing the default Adam.
      warm_start: start each training from the state's parameters (else re-initialise).
      concavity_points: particles at which the c-concavity check runs (0: skipped).
      fresh_observations: draw each mini-batch's observations afresh from
        ``model.sample_observation`` (else reuse the Y^i simulated once per update).

    Numbers (may be traced: ``vmap`` over them runs in one program):

      potential_learning_rate, potential_weight_decay: the default AdamW on f (3e-4, 1).
      transport_learning_rate: the default Adam on T (1e-3).
      divergence_threshold: |smoothed J| above this times n counts as divergence.
      inflation: multiplies the prior particles' anomalies before the update (as ``enkf``'s):
        chaotic models with few particles need a little (e.g. 1.04 on Lorenz-96).
      trend_threshold: the moving average over updates of the normalised innovation (about 1
        while the filter tracks; ``transport/divergence.py``) above this (or below 0.3) means the
        filter lost track: the update then skips training, uses the EnKF and restarts the
        networks (and the iteration schedule) until the average is back in range.
      concavity_step: difference step of the c-concavity check (standardised units).
      prior_smoothing: c in the kernel bandwidth h = c (4 / (n + 2))^(1/(n+4)) N^(-1/(n+4))
        (Silverman's rule, standardised units) of the smoothed prior the map is trained on
        (0: train on the particles themselves; a concrete 0 compiles no smoothing); h is capped
        at 0.9 (shrinkage sqrt(1 - h^2)).
    """
    settings, structure = recipe(
        num_iterations=num_iterations, batch_size=batch_size, inner_steps=inner_steps, width=width,
        num_blocks=num_blocks, activation=activation, enkf_layer=enkf_layer,
        potential_optimizer=potential_optimizer, transport_optimizer=transport_optimizer,
        warm_start=warm_start, divergence_threshold=divergence_threshold,
        trend_threshold=trend_threshold, inflation=inflation, concavity_points=concavity_points, concavity_step=concavity_step,
        prior_smoothing=prior_smoothing, fresh_observations=fresh_observations,
        potential_learning_rate=potential_learning_rate,
        potential_weight_decay=potential_weight_decay,
        transport_learning_rate=transport_learning_rate,
    )
    return OTUpdate(
        init=bind(ot_init, settings, structure=structure),
        apply=bind(ot_apply, settings, structure=structure),
        transport=bind(ot_transport, structure=structure),
        potential=bind(ot_potential, structure=structure),
    )


def recipe(*, num_iterations, batch_size, inner_steps, width, num_blocks, activation, enkf_layer,
           potential_optimizer, transport_optimizer, warm_start, divergence_threshold,
           trend_threshold, inflation, concavity_points, concavity_step, prior_smoothing, fresh_observations,
           potential_learning_rate, potential_weight_decay, transport_learning_rate,
           ) -> tuple[OTSettings, OTStructure]:
    """Validates ``ot()``'s arguments (also ``local_ot()``'s): the traced numbers and the static
    structure."""
    first_iterations, floor_iterations = iteration_schedule(num_iterations)
    if activation not in ACTIVATIONS:
        raise ValueError(f"activation must be one of {sorted(ACTIVATIONS)}, got {activation!r}")
    layer = {False: None, True: "perturbed", "perturbed": "perturbed", "deterministic": "deterministic"}.get(
        enkf_layer if isinstance(enkf_layer, (bool, str)) else None, "invalid")
    if layer == "invalid":
        raise ValueError(f"enkf_layer must be False, True (= 'perturbed') or 'deterministic', got {enkf_layer!r}")
    for name, optimizer in (("potential_optimizer", potential_optimizer),
                            ("transport_optimizer", transport_optimizer)):
        if optimizer is not None and not isinstance(optimizer, optax.GradientTransformation):
            raise TypeError(f"{name} must be an optax.GradientTransformation, got {type(optimizer).__name__}")
    settings = OTSettings(
        potential_learning_rate=check_number("potential_learning_rate", potential_learning_rate, 0.0, strict_minimum=True),
        potential_weight_decay=check_number("potential_weight_decay", potential_weight_decay, 0.0),
        transport_learning_rate=check_number("transport_learning_rate", transport_learning_rate, 0.0, strict_minimum=True),
        divergence_threshold=check_number("divergence_threshold", divergence_threshold, 0.0, strict_minimum=True),
        trend_threshold=check_number("trend_threshold", trend_threshold, 0.0, strict_minimum=True),
        inflation=check_number("inflation", inflation, 1.0),
        concavity_step=check_number("concavity_step", concavity_step, 0.0, strict_minimum=True),
        prior_smoothing=check_number("prior_smoothing", prior_smoothing, 0.0),
    )
    smoothing = is_traced(prior_smoothing) or float(prior_smoothing) > 0
    if smoothing and not fresh_observations:
        raise ValueError("prior_smoothing needs fresh_observations=True (observations of the jittered states)")
    structure = OTStructure(
        first_iterations=first_iterations,
        floor_iterations=floor_iterations,
        batch_size=None if batch_size is None else check_int("batch_size", batch_size, minimum=2),
        inner_steps=check_int("inner_steps", inner_steps),
        width=None if width is None else check_int("width", width),
        num_blocks=check_int("num_blocks", num_blocks, minimum=0),
        activation=activation,
        enkf_layer=layer is not None,
        warm_start=bool(warm_start),
        concavity_points=check_int("concavity_points", concavity_points, minimum=0),
        smoothing=smoothing,
        fresh_observations=bool(fresh_observations),
        potential_optimizer=potential_optimizer,
        transport_optimizer=transport_optimizer,
        deterministic_layer=layer == "deterministic",
    )
    return settings, structure


def iteration_schedule(num_iterations) -> tuple[int, int]:
    """``(first, floor)`` of a budget given as an int (every update) or as ``(first, floor)``
    (``first`` at the first update, halved down to ``floor``); checked, errors name the argument."""
    if isinstance(num_iterations, tuple):
        if len(num_iterations) != 2:
            raise ValueError(f"num_iterations must be an int or (first, floor), got {num_iterations!r}")
        first = check_int("num_iterations[0] (first)", num_iterations[0])
        floor = check_int("num_iterations[1] (floor)", num_iterations[1])
        if floor > first:
            raise ValueError(f"num_iterations (first, floor) needs floor <= first, got {num_iterations}")
        return first, floor
    first = check_int("num_iterations", num_iterations)
    return first, first


def default_sizes(n: int) -> tuple[int, int]:
    """``(width, batch_size)`` of ``ot()``'s networks when not given, for state dimension n.

    Measured on the static example (lambda_w = 0.4, y = 1, N = 1000, 10,000 iterations, W1 to
    the exact marginals; floor 0.037 at n = 10; ``benchmarks/ot_sizes.py``, records in
    ``benchmarks/results/ot_dimension_size_rule/``): at n = 10 width 32 / batch 128 gives 0.37,
    width 64 with batches of 256, 512 and 1024 gives 0.140, 0.120 and 0.091 (f's learning rate
    3e-4), and width 128 nothing over 64 (0.122 at batch 512, three times the cost). The pairs
    seen per iteration are the lever, and one pair carries n coordinates' worth of conditioning
    to learn: the batch grows as 32 n^2 (128 at n = 2, the chapter's setting) up to 1024. Beyond
    that nothing measured helps at n = 10 (two seeds: 0.099 with the rule, 0.105 with batches of
    2048, 0.111 with 20,000 iterations).

    The width grows with n too, as 5 n rounded to a power of two, from 64 up to 256 (64 to
    n = 18, 128 from 19 to 36, 256 from 37). Measured on a GPU (NVIDIA H200, the same two seeds
    for each line, batch 1024; ``benchmarks/gpu_checks.py``, records in
    ``benchmarks/results/gpu/``): at n = 50 widths 64, 128, 256 and 384 give 0.472, 0.332,
    0.155 and 0.163 (the floor 0.036; the EnKF 0.425, SIR 0.930), the worst coordinate 1.30,
    1.30, 0.29 and 0.35; batches of 2048 give 0.492 at width 64 and 0.138 at 384. At n = 20
    width 128 gives 0.126 (on the CPU), 256 0.140 and 384 0.157, against 0.161 with 64 (on the
    CPU); at n = 10 384 gives 0.146 against 0.110 with 64 (on the CPU). A wide network needs the large batch: width 384 with batches of 384
    (the authors' sizes) gives 0.895 at n = 50.
    """
    width = 32 if n <= 2 else min(max(1 << round(math.log2(5 * n)), 64), 256)
    batch = 1 << int(round(math.log2(min(max(32 * n * n, 128), 1024))))
    return width, batch


def sized(structure: OTStructure, n: int) -> OTStructure:
    """The structure with ``default_sizes`` filled in where ``width`` / ``batch_size`` is None
    (static: n is a shape)."""
    if structure.width is not None and structure.batch_size is not None:
        return structure
    width, batch = default_sizes(n)
    return structure._replace(width=structure.width or width, batch_size=structure.batch_size or batch)


# ---- the steps the recipe binds ----


def networks(structure: OTStructure) -> tuple[PotentialNetwork, TransportNetwork]:
    """f and T (flax modules; parameters live in the state)."""
    return (
        PotentialNetwork(structure.width, structure.num_blocks, structure.activation),
        TransportNetwork(structure.width, structure.num_blocks, structure.activation),
    )


def optimizers(settings: OTSettings, structure: OTStructure):
    """``(f's, T's)`` optax transformations: the given ones, else AdamW / Adam of the settings
    (built from traced numbers inside the program, so a learning-rate sweep vmaps)."""
    potential = structure.potential_optimizer
    if potential is None:
        potential = optax.adamw(settings.potential_learning_rate, weight_decay=settings.potential_weight_decay)
    transport = structure.transport_optimizer
    if transport is None:
        transport = optax.adam(settings.transport_learning_rate)
    return potential, transport


def init_training(settings: OTSettings, structure: OTStructure, key: Array, n: int, m: int, dtype) -> TrainingState:
    """Fresh network parameters (in the data's dtype) and optimiser states."""
    potential_net, transport_net = networks(structure)
    potential_optimizer, transport_optimizer = optimizers(settings, structure)
    potential_key, transport_key = jax.random.split(key)
    conditioning_size = m + (context_size(n, m) if structure.contextual else 0)
    x, y = jnp.zeros((1, n), dtype), jnp.zeros((1, conditioning_size), dtype)
    params = SaddleParams(potential_net.init(potential_key, x, y), transport_net.init(transport_key, x, y))
    params = jax.tree.map(lambda leaf: leaf.astype(dtype), params)  # float64 data: float64 nets
    return TrainingState(
        params, potential_optimizer.init(params.potential), transport_optimizer.init(params.transport)
    )


def starting_training(settings: OTSettings, structure: OTStructure, key: Array, n: int, m: int,
                      dtype) -> TrainingState:
    """Where a training starts afresh: the offline-trained map (``structure.anchored``) with
    fresh optimiser states, else random parameters."""
    if not structure.anchored:
        return init_training(settings, structure, key, n, m, dtype)
    params = jax.tree.map(lambda leaf: jnp.asarray(leaf, dtype), settings.anchor)
    potential_optimizer, transport_optimizer = optimizers(settings, structure)
    return TrainingState(params, potential_optimizer.init(params.potential),
                         transport_optimizer.init(params.transport))


def iteration_budget(num_updates: Array, first: int, floor: int) -> Array:
    """Outer iterations of update number ``num_updates``: ``first`` halved that many times,
    not below ``floor``."""
    return jnp.maximum(floor, jnp.right_shift(first, jnp.minimum(num_updates, 30)))


def ot_init(settings: OTSettings, key: Array, particles: Array, model: StateSpaceModel | None = None,
            *, structure: OTStructure) -> OTState:
    if model is None:
        raise ValueError("ot().init needs the model (for the observation dimension): init(key, particles, model)")
    if particles.ndim != 2 or particles.shape[0] < 2:
        raise ValueError(f"particles must have shape [N >= 2, n], got {particles.shape}")
    num, n = particles.shape
    y = jax.eval_shape(model.sample_observation, key, particles[0])
    if y.ndim != 1:
        raise ValueError(f"model.sample_observation must return y[m], got shape {y.shape}")
    m = y.shape[0]
    dtype = particles.dtype
    structure = sized(structure, n)
    return OTState(
        log_weights=uniform_log_weights(particles),
        training=starting_training(settings, structure, key, n, m, dtype),
        standardisation=identity_standardisation(n, m, dtype),
        gain=empty_layer(n, m, dtype, structure.deterministic_layer),
        simulated_observations=jnp.zeros((num, m), dtype),
        num_updates=jnp.zeros((), jnp.int32),
        diverged=jnp.array(False),
        innovation_trend=jnp.ones((), dtype),
        context=jnp.zeros(settings.context_scaling.mean.shape, dtype) if structure.contextual else None,
    )


def ot_apply(settings: OTSettings, key: Array, state: OTState, particles: Array, observation: Array,
             model: StateSpaceModel, *, structure: OTStructure):
    """Shapes checked here; the work is one compiled program (also when called outside jit)."""
    observation = check_apply_arguments(state, particles, observation)
    structure = sized(structure, particles.shape[1])
    return _apply(settings, key, state, particles, observation, model, structure=structure)


def check_apply_arguments(state, particles: Array, observation: Array) -> Array:
    """Checks ``particles[N, n]`` and ``observation[m]`` against the sizes at init (the state's
    log-weights and standardisation); returns the observation in the particles' dtype."""
    n, m = state.standardisation.x_mean.shape[0], state.standardisation.y_mean.shape[0]
    num = state.log_weights.shape[0]
    if jnp.shape(particles) != (num, n):
        raise ValueError(f"particles must have shape ({num}, {n}) like at init, got {jnp.shape(particles)}")
    if jnp.shape(observation) != (m,):
        raise ValueError(f"observation must have shape ({m},), got {jnp.shape(observation)}")
    return jnp.asarray(observation, particles.dtype)


class PriorData(NamedTuple):
    """An update's prior particles (inflated), their simulated observations and standardisation."""

    particles: Array  # [N, n] inflated
    simulated: Array  # [N, m] Y^i ~ h(. | X^i)
    active: Array  # [N] bool
    num_active: Array
    scaling: Standardisation
    observed: Array  # [m] bool: the finite components of y
    xs: Array  # [N, n] standardised particles
    ys: Array  # [N, m] standardised simulated observations, missing components 0


def prior_data(settings, key: Array, log_weights: Array, particles: Array, observation: Array,
               model: StateSpaceModel) -> PriorData:
    """Inflate (by ``settings.inflation``: ``OTSettings`` or any settings with that number),
    simulate Y^i ~ h(. | X^i), standardise over the active (unpadded) particles.
    Missing components (NaN in y) are set to their standardised mean 0 in every training pair
    (and the caller sets them so in y): a constant carries no information, so the map learnt is
    T(x, y_observed)."""
    active = active_mask(log_weights)
    particles = inflate(particles, active, settings.inflation)
    simulated = simulate_observations(key, model, particles)
    scaling = standardisation(particles, simulated, active)
    observed = jnp.isfinite(observation)
    return PriorData(particles, simulated, active, jnp.sum(active), scaling, observed,
                     scaling.standardise_x(particles), jnp.where(observed, scaling.standardise_y(simulated), 0.0))


def observed_simulator(model: StateSpaceModel, observed: Array, scaling: Standardisation) -> Callable:
    """``sample_observation(key, x)`` with the missing components (``observed`` False) held at
    their mean, which standardises to 0: a constant carries no information."""

    def sample_observation(key, x):
        return jnp.where(observed, model.sample_observation(key, x), scaling.y_mean)

    return sample_observation


def training_data(prior: PriorData, prior_smoothing, smoothing: bool) -> TrainingData:
    """What the mini-batches are drawn from: the prior's standardised pairs, the active
    particles first, and the smoothing kernel (its Cholesky factor only where ``smoothing``)."""
    n = prior.xs.shape[1]
    return TrainingData(
        prior.xs, prior.ys,
        active_index=active_first(prior.active),  # mini-batches draw indices below num_active
        num_active=prior.num_active,
        bandwidth=smoothing_bandwidth(prior_smoothing, prior.num_active, n, prior.xs.dtype),
        correlation_factor=correlation_cholesky(prior.xs, prior.active) if smoothing else None,
        scaling=prior.scaling,
    )


def trend_and_budget(state, prior: PriorData, observation: Array, trend_threshold, first: int, floor: int):
    """``(trend, lost, budget)``: the innovation trend after this update, whether the filter has
    lost track, and this update's iterations (the halving schedule from ``state.num_updates``;
    none while lost)."""
    trend = innovation_trend(state.innovation_trend, prior.simulated, observation, prior.active)
    lost = lost_track(trend, trend_threshold, jnp.sum(jnp.isfinite(observation)))
    budget = jnp.where(lost, 0, iteration_budget(state.num_updates, first, floor))
    return trend, lost, budget


def train(settings: OTSettings, structure: OTStructure, train_key: Array, reset_key: Array, state,
          prior: PriorData, observation: Array, sample_batch: Callable, sizes: tuple[int, int],
          cost_from_layer: bool = False):
    """Saddle-point training, warm-started from ``state.training`` (unless ``warm_start=False``)
    and budgeted by the halving schedule; none while the filter has lost track (the trend of its
    innovations, ``transport/divergence.py``: the EnKF serves until it comes down).
    ``sizes``: the networks' (x, y) input widths. Returns ``(training, trace, trend, lost)``.
    With no iterations at all (an offline map used as is) nothing is trained or restarted, and
    the trace is empty: the caller fills in the map's J on this prior."""
    trend, lost, budget = trend_and_budget(state, prior, observation, settings.trend_threshold,
                                           structure.first_iterations, structure.floor_iterations)
    if structure.first_iterations == 0:
        dtype = prior.xs.dtype
        return state.training, TrainingTrace(jnp.zeros((0,), dtype), jnp.zeros((), dtype), jnp.array(True)), trend, lost
    potential_net, transport_net = networks(structure)
    training = state.training
    if (structure.anchored and structure.restart) or not structure.warm_start:
        training = starting_training(settings, structure, reset_key, *sizes, prior.xs.dtype)
    potential_optimizer, transport_optimizer = optimizers(settings, structure)
    training, trace = train_saddle(
        train_key, training, sample_batch, budget,
        potential_net=potential_net, transport_net=transport_net,
        potential_optimizer=potential_optimizer, transport_optimizer=transport_optimizer,
        inner_steps=structure.inner_steps, enkf_layer=structure.enkf_layer,
        record_length=structure.first_iterations, cost_from_layer=cost_from_layer,
    )
    return training, trace, trend, lost


def fallback_gain(model, particles, xs, ys, scaling, observed, active, layer_gain=None):
    """The fallback EnKF's gain in standardised coordinates: with additive Gaussian noise of
    known R, ``ot_filter.enkf()``'s Cov(X, h) (Cov(h) + R)^{-1} (the sample Cov(Y) of N = 50
    simulated observations of Lorenz-96's 40 put the global OT filter, which falls back every
    20-50 steps there, at RMSE 3.3 instead of 1.15); else the perturbed layer's gain
    ``layer_gain`` when there is one, else the gain of the simulated pairs. A missing component
    gets a zero column."""
    if model.has_gaussian_observation_noise:
        predicted = jax.vmap(model.observation_function)(particles)
        predicted = jnp.where(observed, scaling.standardise_y(predicted), 0.0)
        noise_cov = dense_noise_cov(model.observation_noise_cov).astype(xs.dtype)
        noise_cov = noise_cov / jnp.outer(scaling.y_scale, scaling.y_scale)
        noise_cov = jnp.where(observed[:, None] & observed[None, :], noise_cov, jnp.eye(observed.shape[0], dtype=xs.dtype))
        return known_noise_gain(xs, predicted, noise_cov, active)
    if layer_gain is not None:
        return layer_gain
    return enkf_gain(xs, ys, active)


def enkf_fallback(xs, y_standard, ys, gain, scaling, active, num_active):
    """The stochastic EnKF's posterior particles (original coordinates) with the update's own
    simulated observations ``ys`` and the standardised ``gain``; padding at the posterior mean, as
    the EnKF leaves it. Returns ``(particles, standardised particles)``."""
    enkf_standard = transport_input(xs, y_standard, ys, gain)
    enkf_particles = scaling.restore_x(enkf_standard)
    enkf_mean, _ = masked_mean_and_anomalies(enkf_particles, active, num_active)
    return jnp.where(active[:, None], enkf_particles, enkf_mean), enkf_standard


@jax.jit(static_argnames=("structure",))
def _apply(settings, key, state, particles, observation, model, structure):
    """The recipe: simulate, standardise, train, transport, check, fall back."""
    n = particles.shape[1]
    simulate_key, train_key, _, reset_key = jax.random.split(key, 4)
    potential_net, transport_net = networks(structure)

    # 1. Training data: Y^i ~ h(. | X^i), both standardised over the active (unpadded) particles.
    prior = prior_data(settings, simulate_key, state.log_weights, particles, observation, model)
    particles, simulated, active, num_active, scaling, observed, xs, ys = prior

    sample_observation = observed_simulator(model, observed, scaling)
    context = prior_context(settings, structure, scaling, xs, active)
    data = training_data(prior, settings.prior_smoothing, structure.smoothing)

    # The layer from all particles (the perturbed layer's gain is re-estimated on each
    # mini-batch in training; the deterministic layer's moments always come from here).
    gain = (fit_layer(xs, ys, active, structure.deterministic_layer) if structure.enkf_layer
            else empty_layer(n, ys.shape[1], particles.dtype))
    batch_layer = gain if structure.deterministic_layer else None

    # 2. Saddle-point training (none while the filter has lost track).
    training, trace, trend, lost = train(
        settings, structure, train_key, reset_key, state, prior, observation,
        lambda batch_key: sample_batch(
            batch_key, data, sample_observation, batch_size=structure.batch_size,
            smoothing=structure.smoothing, fresh_observations=structure.fresh_observations,
            enkf_layer=structure.enkf_layer,
        )._replace(context=context, gain=batch_layer),
        (n, ys.shape[1]),
    )
    params = training.params

    # The map's J terms on the prior's own first pairs (``own_pairs``: nothing drawn). f(x, y)
    # gives the potential's spread (a diagnostic); without training, J stands in for the empty
    # trace so that the loss test of the divergence check still sees the map. (What is not used
    # compiles away.)
    check = own_pairs(data, CHECK_ROWS)._replace(context=context, gain=batch_layer)
    joint, independent = saddle_terms(
        lambda x, y: potential_net.apply(params.potential, x, y),
        lambda x, y: transport_net.apply(params.transport, x, y),
        check, batch_gain(check, structure.enkf_layer),
    )
    counted = jnp.arange(CHECK_ROWS) < num_active  # own_pairs repeats rows when fewer are active
    if structure.first_iterations == 0:
        value = jnp.mean(joint, where=counted) + jnp.mean(independent, where=counted)
        trace = trace._replace(smoothed_loss=value, finite=jnp.isfinite(value))

    # 3. Transport the particles to the actual observation.
    y_standard = jnp.where(observed, scaling.standardise_y(observation), 0.0)
    moved = _transport_standardised(structure, params.transport, xs, y_standard, ys, gain, context)

    # 4. Checks: divergence (loss, spread, posterior predictive) and c-concavity.
    checked = data.active_index[:CHECK_ROWS]
    z = predictive_check(jax.random.fold_in(key, 4), model, scaling.restore_x(moved[checked]), observation,
                         active[checked])
    diverged = lost | divergence_test(trace.finite, trace.smoothed_loss, settings.divergence_threshold, n,
                                      moved, active, z, xs)
    min_eigenvalue, violation = _concavity_check(settings, structure, params.potential, xs, ys, data, context)

    # 5. Fall back where training diverged: the stochastic EnKF with this update's own simulated
    #    observations (padding at the posterior mean, as the EnKF leaves it), and restart the
    #    networks. A map used as is also falls back where it did not condition (far wider than
    #    the EnKF: ``wider_than_enkf``).
    layer_gain = gain if structure.enkf_layer and not structure.deterministic_layer else None
    enkf_particles, enkf_standard = enkf_fallback(
        xs, y_standard, ys, fallback_gain(model, particles, xs, ys, scaling, observed, active, layer_gain),
        scaling, active, num_active)
    if structure.first_iterations == 0:
        diverged = diverged | (jnp.any(observed) & wider_than_enkf(moved, enkf_standard, active))
    posterior = use_where(~diverged, scaling.restore_x(moved), enkf_particles)
    # An observation with nothing finite carries no information: the particles stay
    # (run_filter skips such steps before getting here).
    posterior = jnp.where(jnp.any(observed), posterior, particles)
    if structure.first_iterations:  # an offline map used as is has nothing to restart
        fresh = starting_training(settings, structure, reset_key, n, ys.shape[1], particles.dtype)
        training = use_where(diverged, fresh, training)

    state = OTState(
        log_weights=state.log_weights,
        training=training,
        standardisation=scaling,
        gain=gain,
        simulated_observations=simulated,
        num_updates=jnp.where(diverged, 0, state.num_updates + 1),  # fresh networks: full budget
        diverged=diverged,
        innovation_trend=trend,
        context=context,
    )
    info = OTInfo(
        loss=trace.loss,
        final_loss=finite_or_inf(trace.smoothed_loss),
        diverged=diverged,
        min_hessian_eigenvalue=finite_or_inf(min_eigenvalue),
        concavity_violation=finite_or_inf(violation),
        potential_spread=finite_or_inf(jnp.std(joint, where=counted)),
        predictive_z=finite_or_inf(z),
        innovation_trend=trend,
    )
    return posterior, state, info


def prior_context(settings: OTSettings, structure: OTStructure, scaling: Standardisation, xs: Array,
                  active: Array) -> Array | None:
    """The prior's normalised context features (``transport/context.py``); None unless the
    networks read them."""
    if not structure.contextual:
        return None
    return settings.context_scaling.normalise(context_features(scaling, xs, active))


def _concavity_check(settings, structure, potential_params, xs, ys, data, context=None):
    """(smallest Hessian eigenvalue, fraction of violations) at the first checked active pairs."""
    if not structure.concavity_points:  # min over no points
        return jnp.array(jnp.inf, xs.dtype), jnp.zeros((), xs.dtype)
    potential_net, _ = networks(structure)
    checked = min(structure.concavity_points, xs.shape[0])
    points = data.active_index[:checked]
    eigenvalues = c_concavity_min_eigenvalue(
        lambda x, y: potential_net.apply(potential_params, x, conditioning(y, context)),
        xs[points], ys[points], settings.concavity_step,
    )
    counted = jnp.arange(checked) < data.num_active
    min_eigenvalue = jnp.min(jnp.where(counted, eigenvalues, jnp.inf))
    violation = jnp.sum(counted & (eigenvalues < 0)) / jnp.minimum(checked, data.num_active)
    return min_eigenvalue, violation


def _transport_standardised(structure, transport_params, xs, y_standard, ys, gain, context=None):
    _, transport_net = networks(structure)
    y_rows = jnp.broadcast_to(y_standard, ys.shape)
    inputs = transport_input(xs, y_rows, ys, gain if structure.enkf_layer else None)
    return transport_net.apply(transport_params, inputs, conditioning(y_rows, context))


def ot_transport(state: OTState, particles: Array, observation: Array, simulated: Array | None = None,
                 *, structure: OTStructure) -> Array:
    scaling = state.standardisation
    if particles.ndim != 2 or particles.shape[1] != scaling.x_mean.shape[0]:
        raise ValueError(
            f"particles must have shape [N, {scaling.x_mean.shape[0]}], got {particles.shape}"
        )
    m = scaling.y_mean.shape[0]
    observation = jnp.asarray(observation, particles.dtype)
    if observation.ndim not in (1, 2) or observation.shape[-1] != m:
        raise ValueError(f"observation must have shape [{m}], [N, {m}] or [K, {m}], got {observation.shape}")
    if simulated is None:
        simulated = state.simulated_observations
    if simulated.shape != (particles.shape[0], m):
        raise ValueError(
            f"simulated observations must have shape {(particles.shape[0], m)} (one per particle), "
            f"got {simulated.shape}; pass the particles given to the last apply"
        )
    return _transport(state, particles, observation, simulated, structure=sized(structure, particles.shape[1]))


@jax.jit(static_argnames=("structure",))
def _transport(state, particles, observation, simulated, structure):
    scaling = state.standardisation
    xs, ys = scaling.standardise_x(particles), scaling.standardise_y(simulated)
    y_standard = scaling.standardise_y(observation)

    def move(y_rows):
        moved = _transport_standardised(structure, state.training.params.transport, xs, y_rows, ys, state.gain,
                                        state.context)
        return scaling.restore_x(moved)

    if observation.ndim == 1 or observation.shape[0] == particles.shape[0]:
        return move(y_standard)
    return jax.vmap(move)(y_standard)


def ot_potential(state: OTState, x: Array, y: Array, *, structure: OTStructure) -> Array:
    scaling = state.standardisation
    potential_net, _ = networks(sized(structure, scaling.x_mean.shape[0]))
    return potential_net.apply(state.training.params.potential, scaling.standardise_x(x),
                               conditioning(scaling.standardise_y(y), state.context))


def finite_or_inf(value: Array) -> Array:
    return jnp.where(jnp.isnan(value), jnp.inf, value)
