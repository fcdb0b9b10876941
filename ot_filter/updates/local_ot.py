"""The localised OT Bayes update: one conditional map shared by every state coordinate.

The global update (``updates/ot.py``) learns T(x[n], y[m]) from N particles: its networks and
the data they need grow with n, and above n of about 10 a default-sized map no longer resolves
the posterior. Here each state coordinate i sees only its local window
(``localisation.local_windows``): the state coordinates W_i within ``state_radius`` (itself
first) and the observations O_i within ``radius``. ONE pair of networks, shared by all
coordinates, learns the local conditional map

    T(x_W, y_O) -> x_W',   with max-min objective of ``transport/saddle.py`` on local pairs,

and coordinate i takes the first component (itself) of T(X^p_{W_i}, y_{O_i}), as the LETKF keeps
the centre of each local analysis. Every particle gives n local pairs, so a training step draws
its mini-batch of (particle, coordinate) pairs from N n of them; the independent copy Xbar of a
pair at coordinate i is another particle's window at the same i (the independent coupling of that
coordinate's local problem). The per-iteration cost does not depend on n: only the final
transport (N n small forward passes) and the local gains grow, linearly.

Structure that makes this exact or approximate:

- Coordinates that are independent a priori and observed separately (the chapter's examples):
  ``radius = state_radius = 0`` gives windows {i} and {y_i}; the local problem IS coordinate i's
  Bayes problem. Where the coordinates' priors are alike (one update from N(0, I)) one map is
  exact in structure; in a filter they come to differ in shape, and the networks also read each
  window's prior quantiles (``prior_context``), so that one map serves them all.
- A lattice (Lorenz-96's ring): windows mean the same relative positions everywhere, so sharing
  assumes the local problems are alike (translation invariance; per-coordinate standardisation
  absorbs different scales). Observations beyond ``radius`` are ignored, as in the LETKF.

Local observation slots that are padding (a coordinate with fewer observations within reach) or
missing at this step (NaN in y) are set to their standardised mean 0; the network also reads the
slot mask, so that slots with different offsets (every second coordinate observed) are told
apart.

EnKF layer (``enkf_layer=True``): each coordinate's local gain K_i = Cov(X_W, Y_O) Cov(Y_O)^-1
from all particles, and T's input is x_W + K_i (y_O - Y_O). The transport cost is measured from
that input (``saddle.transport_cost``): T corrects the local EnKF analysis and is the identity
where it is already right. The same local gain gives the fallback when training diverges: the
local perturbed-observation EnKF (the layer alone), whose cost is also linear in n (the global
EnKF fallback of ``ot()`` would not localise).

Deterministic layer (``enkf_layer="deterministic"``, models with additive Gaussian noise): each
window's local ETKF (``lib.transform``; the window's observations, unweighted) gives every prior
particle q its deterministic analysis anomaly d_q and the mean gain K_i, and T's input for a copy
q and an observation y is m_W + d_q + K_i (y_O - mean h(X)_O): at the actual observation the
LETKF's analysis (hard windows; with ``taper="gaspari_cohn"`` the observation error variances
are divided by the Gaspari-Cohn taper whose support is the windows' radius: the tapered LETKF),
and for y drawn with an independent x the prior's first two moments (approximately with a
taper), as the map's training needs. It has no perturbation noise, which is what held the
perturbed layer back on Lorenz-96 (``benchmarks/ot_lorenz96.py``). A state-space square root per
window (``saddle.DeterministicLayer``, right for the global update) does not serve here: each
coordinate's own transform mixes its neighbours' anomalies differently, the analysis loses the
cross-covariances, and the filter diverged. The ensemble transform acts on the members, which
neighbouring windows share.

Offline map (``initial_map``): where the windows' local problems are alike from step to step,
the shared map can be trained once on the local pairs of many forecast ensembles
(``amortised.local``) and every step starts from it, or uses it as is.

Training has no smoothed prior: the observations of a jittered state would need the whole
state. Fresh observations (``fresh_observations=True``, models with additive Gaussian noise) need
only the window: a pair's observation slots are drawn afresh at every mini-batch as h(X)_O plus
noise of R[O, O], so that the map does not learn the one noise draw each pair was simulated
with (10,000 iterations of 512 see each pair 2,560 times at n = 2 and N = 1000, 102 times at
n = 50). The numbers and the rest of the structure are ``ot()``'s (``updates.ot.recipe``).
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ot_filter.lib.ensemble import masked_mean_and_anomalies
from ot_filter.lib.fallback import use_where
from ot_filter.lib.static import bind
from ot_filter.lib.transform import etkf_transform
from ot_filter.lib.validation import check_int, is_traced
from ot_filter.lib.weights import active_first, active_mask, uniform_log_weights
from ot_filter.localisation import TAPERS, LocalWindows, taper_support, taper_weights
from ot_filter.model import StateSpaceModel
from ot_filter.transport.divergence import CHECK_ROWS
from ot_filter.transport.divergence import diverged as divergence_test
from ot_filter.transport.divergence import predictive_z as predictive_check
from ot_filter.transport.saddle import Batch, SaddleParams, TrainingState, enkf_gain, transport_input
from ot_filter.transport.standardisation import Standardisation, identity_standardisation
from ot_filter.updates.ot import (
    OTInfo,
    OTSettings,
    OTStructure,
    check_apply_arguments,
    finite_or_inf,
    init_training,
    networks,
    prior_data,
    recipe,
    starting_training,
    train,
)

Array = jax.Array

__all__ = ["LocalOTSettings", "LocalOTState", "LocalOTUpdate", "local_ot"]


class LocalOTSettings(NamedTuple):
    """The localised update's numbers and windows (pytree leaves)."""

    ot: OTSettings
    windows: LocalWindows
    context_levels: Array  # [Q] quantile levels of the local prior given to the networks (Q may be 0)
    layer_weights: Array  # [n, K] the deterministic layer's taper of each window slot (0 on padding)


class LocalOTState(NamedTuple):
    log_weights: Array  # [N], uniform
    training: TrainingState  # the shared networks' parameters and optimiser states
    standardisation: Standardisation  # of the last training data (global, per coordinate)
    gain: Array  # [n, S, 2K] local EnKF gains (standardised; zeros on the mask columns)
    simulated_observations: Array  # [N, m] Y^i ~ h(. | X^i) of the last update
    num_updates: Array  # updates since the networks were (re-)initialised
    diverged: Array
    innovation_trend: Array  # moving average of the normalised innovation (1: tracking)


class LocalOTUpdate(NamedTuple):
    """``BayesUpdate``'s ``init``/``apply`` (``info`` is an ``OTInfo``; the c-concavity check is
    off: +inf and 0), plus ``transport(state, particles, observation[m], model=None)``: the prior
    particles of the last ``apply`` moved by its trained map for another observation (the
    deterministic layer needs the model)."""

    init: Callable[..., LocalOTState]
    apply: Callable[..., tuple[Array, LocalOTState, OTInfo]]
    transport: Callable[..., Array]


def local_ot(
    windows: LocalWindows,
    num_iterations: int | tuple[int, int] = (10_000, 500),
    batch_size: int = 512,
    inner_steps: int = 10,
    width: int = 32,
    num_blocks: int = 1,
    activation: str = "relu",
    enkf_layer: bool | str = False,
    taper: str = "step",
    potential_optimizer=None,
    transport_optimizer=None,
    warm_start: bool = True,
    divergence_threshold: float = 10.0,
    trend_threshold: float = 10.0,
    inflation: float = 1.0,
    prior_context: int = 8,
    location_context: bool = False,
    map_knots: int | None = None,
    fresh_observations: bool = False,
    potential_learning_rate: float = 1e-4,
    potential_weight_decay: float = 1.0,
    transport_learning_rate: float = 1e-3,
    initial_map: SaddleParams | None = None,
) -> LocalOTUpdate:
    """Builds the localised OT update.

    Args:
      windows: ``localisation.local_windows(model.geometry, radius, state_radius)``; e.g.
        radius 0 for coordinates that are independent and observed one by one.
      enkf_layer: False, True (= ``"perturbed"``) or ``"deterministic"`` (module docstring; needs
        ``model.observation_function`` and ``observation_noise_cov``, whose diagonal it uses).
      taper: how the deterministic layer weighs a window's observations: ``"step"`` (all alike:
        the LETKF with a step taper of the windows' radius) or ``"gaspari_cohn"``, whose support
        is the windows' radius (the LETKF with ``localisation(geometry, radius / 3.65)``, its
        length scale): observation error variances divided by the taper, as the LETKF's
        R-localisation does. T still reads every observation of the window.
      prior_context: Q > 0 gives the networks each window coordinate's prior quantiles at levels
        (k + 1/2) / Q (standardised, minus their mean over the coordinates): one shared map then
        serves coordinates whose priors differ in shape (a filter's coordinates after different
        observations), not only in location and scale (default 8). 0: the coordinates' local
        problems are taken to be alike.
      location_context: the networks also read where each window sits in the model's own
        coordinates: arcsinh of the mean and the log of the spread of its state coordinates
        and of its observations' simulated values (what standardisation hides: with y = x^2,
        a window near 0 and one at 8 look alike once standardised, yet one observation is
        ambiguous in sign and the other sharp).
      map_knots: where a window has one state coordinate, T's input for every particle is that
        coordinate and its conditioning is the same for all (the actual observation, the
        window's context): T is then evaluated at ``map_knots`` points spanning the particles
        and interpolated linearly (``tabulated``), ``map_knots`` network evaluations a window
        instead of N. Training is not affected. Default: ``MAP_KNOTS`` for such windows when an
        offline map is used as is (``num_iterations=0``: T's forward pass is then the step's
        main cost), else 0 (T at every particle; wider windows cannot be tabulated).
      fresh_observations: draw each mini-batch's local observations afresh, h(X)_O plus noise
        of R's window block R[O, O] (module docstring; needs ``model.observation_function`` and
        ``observation_noise_cov``), instead of the one observation simulated per particle. Not
        for the offline trainer, whose bank stores the simulated ones. It helps where a training
        sees each local pair many times (iterations x batch / (N n)): one update of 10,000
        iterations on the static example took W1 from 0.069 to 0.044 at n = 2 (floor 0.040) and
        from 1.60 to 1.43 times the floor at n = 10 (not resolved on held-out prior samples), and
        changed nothing at n = 20 and 50, nor in the filters measured (short trainings a step;
        ``docs/ot_at_scale.md``). Off by default; unused by a map used as is.
      initial_map: the shared networks' parameters trained offline (``amortised.train_local_map``,
        built with the same sizes and windows; ``amortised.amortised_local_ot`` builds this update
        from a recorded ``LocalMap``): every training starts from them (with fresh
        optimiser states) instead of random ones: the first, one after a divergence, and every
        step's with ``warm_start=False``. ``num_iterations=0`` then uses the map as is (one
        forward pass a step, no training).
      Every other argument is ``ot()``'s (``batch_size`` counts local pairs), with this update's
      own defaults: width 32, batches of 512 local pairs and f's rate 1e-4, whatever n (the
      local problem's size does not grow with n; ``ot()``'s size rule does not apply). Batches of
      512 rather than 128 (0.2.19): as for the global map, the pairs a step sees are the lever;
      on the static example (six training keys) every key is then under twice the floor at
      n = 10, 20 and 50, at 3-4 times the seconds of an update on a CPU (``docs/ot_at_scale.md``).
    """
    if not isinstance(windows, LocalWindows):
        raise TypeError("windows must be a localisation.LocalWindows: "
                        f"local_windows(model.geometry, radius, state_radius), got {type(windows).__name__}")
    # The local map's sizes are given (its inputs are a window, whatever n): not ot()'s rule.
    batch_size, width = check_int("batch_size", batch_size, minimum=2), check_int("width", width)
    as_is = initial_map is not None and not isinstance(num_iterations, tuple) and num_iterations == 0
    settings, structure = recipe(
        num_iterations=1 if as_is else num_iterations, batch_size=batch_size, inner_steps=inner_steps, width=width,
        num_blocks=num_blocks, activation=activation, enkf_layer=enkf_layer,
        potential_optimizer=potential_optimizer, transport_optimizer=transport_optimizer,
        warm_start=warm_start, divergence_threshold=divergence_threshold,
        trend_threshold=trend_threshold, inflation=inflation, concavity_points=0,
        concavity_step=0.1, prior_smoothing=0.0, fresh_observations=bool(fresh_observations) and not as_is,
        potential_learning_rate=potential_learning_rate,
        potential_weight_decay=potential_weight_decay, transport_learning_rate=transport_learning_rate,
    )
    if taper not in TAPERS:
        raise ValueError(f"taper must be one of {TAPERS}, got {taper!r}")
    if taper != "step" and not structure.deterministic_layer:
        raise ValueError("taper weighs the deterministic layer's observations: give enkf_layer='deterministic'")
    structure = structure._replace(location_context=bool(location_context),
                                   map_knots=_map_knots(map_knots, windows, as_is))
    if initial_map is not None:
        if not isinstance(initial_map, SaddleParams):
            raise TypeError(f"initial_map must be a SaddleParams (amortised.train_local_map), got "
                            f"{type(initial_map).__name__}")
        settings = settings._replace(anchor=initial_map)
        structure = structure._replace(anchored=True, restart=not warm_start)
        if as_is:
            structure = structure._replace(first_iterations=0, floor_iterations=0)
    levels = (jnp.arange(check_int("prior_context", prior_context, minimum=0)) + 0.5) / max(prior_context, 1)
    numbers = LocalOTSettings(settings, windows, levels, _layer_weights(windows, taper))
    return LocalOTUpdate(
        init=bind(local_ot_init, numbers, structure=structure),
        apply=bind(local_ot_apply, numbers, structure=structure),
        transport=bind(local_ot_transport, numbers, structure=structure),
    )


# Knots of a tabulated one-coordinate map. A ReLU map is piecewise linear in its one input, so
# linear interpolation is exact except in the knot intervals that hold a kink. On the dynamic
# example's offline maps (n = 2, 10, 50; docs/amortised.md, "The localised update with a map trained
# offline") the filters' W1 moved by at most 0.001 (paired over 10 truths). The online filter's
# moved by 0.014 +- 0.008: its map changes at every step and costs far more to train than to
# apply, so the default tabulates only a map used as is.
MAP_KNOTS = 128


def _map_knots(map_knots: int | None, windows: LocalWindows, as_is: bool) -> int:
    one_coordinate = windows.state.shape[1] == 1
    if map_knots is None:
        return MAP_KNOTS if one_coordinate and as_is else 0
    map_knots = check_int("map_knots", map_knots, minimum=0)
    if map_knots == 1:
        raise ValueError("map_knots must be 0 (T at every particle) or at least 2")
    if map_knots and not one_coordinate:
        raise ValueError(f"map_knots tabulates a map of one state coordinate; these windows have "
                         f"{windows.state.shape[1]} (state_radius > 0): give map_knots=0")
    return map_knots


def _layer_weights(windows: LocalWindows, taper: str) -> Array:
    """``[n, K]``: the taper of each window slot, its support the windows' radius."""
    if taper == "step":
        return windows.observations_valid.astype(float)
    length_scale = windows.radius / taper_support(1.0, taper)
    return taper_weights(windows.observation_distances, length_scale, taper) * windows.observations_valid


def window_sizes(windows: LocalWindows) -> tuple[int, int, int]:
    """(n, S, K): coordinates, state-window and observation-window sizes."""
    return windows.state.shape[0], windows.state.shape[1], windows.observations.shape[1]


def conditioning_size(numbers: LocalOTSettings, structure: OTStructure) -> int:
    """Width of the networks' conditioning input: local observations, their mask, the context
    (prior quantiles, and the location features of ``location_context``)."""
    _, window, reach = window_sizes(numbers.windows)
    location = 2 * (window + reach) if structure.location_context else 0
    return 2 * reach + window * numbers.context_levels.shape[0] + location


def local_ot_init(numbers: LocalOTSettings, key: Array, particles: Array,
                  model: StateSpaceModel | None = None, *, structure: OTStructure) -> LocalOTState:
    if model is None:
        raise ValueError("local_ot().init needs the model (for the observation dimension): "
                         "init(key, particles, model)")
    n, window, _ = window_sizes(numbers.windows)
    if particles.ndim != 2 or particles.shape[0] < 2 or particles.shape[1] != n:
        raise ValueError(f"particles must have shape [N >= 2, {n}] (the windows' n), got {particles.shape}")
    m = jax.eval_shape(model.sample_observation, key, particles[0]).shape[0]
    if not is_traced(numbers.windows.observations) and int(np.max(np.asarray(numbers.windows.observations))) >= m:
        raise ValueError(f"the windows index observations beyond the model's m = {m}: "
                         "build them from this model's geometry")
    dtype = particles.dtype
    return LocalOTState(
        log_weights=uniform_log_weights(particles),
        training=_starting_training(numbers, structure, key, window, dtype),
        standardisation=identity_standardisation(n, m, dtype),
        gain=jnp.zeros((n, window, conditioning_size(numbers, structure)), dtype),
        simulated_observations=jnp.zeros((particles.shape[0], m), dtype),
        num_updates=jnp.zeros((), jnp.int32),
        diverged=jnp.array(False),
        innovation_trend=jnp.ones((), dtype),
    )


def local_update_parts(update: LocalOTUpdate) -> tuple[LocalOTSettings, OTStructure]:
    """``(numbers, structure)`` a ``local_ot()`` update was built with (the offline trainer's)."""
    if not isinstance(update, LocalOTUpdate):
        raise TypeError(f"update must be a local_ot() update, got {type(update).__name__}")
    return update.apply.args[0], update.apply.func.keywords["structure"]


def _starting_training(numbers: LocalOTSettings, structure: OTStructure, key: Array, window: int,
                       dtype) -> TrainingState:
    """Random networks, or the offline map's (``initial_map``) after checking its shapes."""
    conditioning = conditioning_size(numbers, structure)
    if structure.anchored:
        expected = jax.eval_shape(lambda k: init_training(numbers.ot, structure, k, window, conditioning, dtype).params,
                                  key)
        given = jax.tree.map(lambda leaf: jax.ShapeDtypeStruct(jnp.shape(leaf), dtype), numbers.ot.anchor)
        if jax.tree.structure(given) != jax.tree.structure(expected) or any(
                a.shape != b.shape for a, b in zip(jax.tree.leaves(given), jax.tree.leaves(expected))):
            raise ValueError("initial_map does not fit these networks and windows: train it with the same width, "
                             "num_blocks, windows and prior_context")
    return starting_training(numbers.ot, structure, key, window, conditioning, dtype)


def local_ot_apply(numbers: LocalOTSettings, key: Array, state: LocalOTState, particles: Array,
                   observation: Array, model: StateSpaceModel, *, structure: OTStructure):
    """Shapes checked here; the work is one compiled program."""
    observation = check_apply_arguments(state, particles, observation)
    return _apply(numbers, key, state, particles, observation, model, structure=structure)


class _LocalData(NamedTuple):
    """The standardised local pairs of one update."""

    x: Array  # [N, n, S] each particle's window of each coordinate
    y: Array  # [N, n, C] its simulated local observations, the slot mask and the prior context
    observation: Array  # [n, C] the actual local observations, the slot mask and the context
    gain: Array  # [n, S, C] (zero on the mask and context columns: constant per coordinate)
    layer_x: Array  # [N, n, S] and
    layer_y: Array  # [N, n, C]: the layer's input is layer_x[q] + gain (y - layer_y[q]) for copy q:
    #                 x and y (the perturbed layer), or m + d_q and the mean h(X) (deterministic)
    predicted: Array | None = None  # [N, n, K] h(X) on the observation slots (0 where masked) and
    noise_factor: Array | None = None  # [n, K, K] Cholesky factor of the slots' noise covariance
    #                                    (rows of masked slots 0): fresh observations


def local_prior_quantiles(xs: Array, active: Array, levels: Array) -> Array:
    """``[n, Q]``: each coordinate's quantiles at ``levels[Q]`` over the active rows of ``xs``."""
    num_active = jnp.sum(active, dtype=jnp.int32)
    ordered = sort_columns(jnp.where(active[:, None], xs, jnp.inf))
    index = jnp.clip(jnp.floor(levels * num_active).astype(jnp.int32), 0, num_active - 1)
    return ordered[index].T


def sort_columns(xs: Array) -> Array:
    """``jnp.sort(xs, axis=0)`` of floats without NaN, sorted as integers: the bits of a float,
    with a negative one's magnitude bits flipped, order as the floats do. XLA's CPU sort of the
    integers is 3.7 times as fast (at n = 10, N = 1000, the float sort cost 2.7 times the EnKF's
    whole step)."""
    integer = {4: jnp.int32, 8: jnp.int64}[xs.dtype.itemsize]
    magnitude = jnp.iinfo(integer).max

    def flip(bits):  # an involution
        return bits ^ (jnp.right_shift(bits, 8 * xs.dtype.itemsize - 1) & magnitude)

    keys = flip(jax.lax.bitcast_convert_type(xs, integer))
    return jax.lax.bitcast_convert_type(flip(jax.lax.sort(keys, dimension=0, is_stable=False)), xs.dtype)


def local_data(numbers: LocalOTSettings, xs: Array, ys: Array, y_standard: Array, observed: Array,
                active: Array, layer: tuple[Array, Array] | None = None,
                location: Standardisation | None = None, fresh: tuple[Array, Array] | None = None) -> _LocalData:
    """Windows of standardised particles ``xs[N, n]`` and observations ``ys[N, m]``; missing
    components (``observed[m]`` False) and padding are 0 with mask 0. ``layer``: the standardised
    ``h(X)[N, m]`` and noise variances ``[m]`` of the deterministic layer (None: perturbed);
    ``fresh``: ``h(X)[N, m]`` and the noise covariance (``[m]`` diagonal or ``[m, m]``) for drawing
    fresh observations (None: none)."""
    windows = numbers.windows
    mask = (windows.observations_valid & observed[windows.observations]).astype(xs.dtype)  # [n, K]
    quantiles = local_prior_quantiles(xs, active, numbers.context_levels)  # [n, Q]
    # Deviations from the coordinates' mean profile: nearly 0 where the local priors are alike
    # (then the context costs the networks nothing), the shape difference where they are not.
    quantiles = quantiles - jnp.mean(quantiles, axis=0)
    context = (quantiles[windows.state] * windows.state_valid[..., None]).reshape(mask.shape[0], -1)
    if location is not None:
        context = jnp.concatenate([context, _location_features(location, windows, mask)], axis=-1)

    def local_y(y_row):
        return jnp.concatenate([y_row[windows.observations] * mask, mask, context], axis=-1)

    x = xs[:, windows.state] * windows.state_valid.astype(xs.dtype)
    y = jax.vmap(local_y)(ys)
    noise = {}
    if fresh is not None:
        predicted, covariance = fresh
        noise = dict(predicted=jnp.where(mask > 0, predicted[:, windows.observations], 0.0),
                     noise_factor=_window_noise_factor(covariance, windows.observations, mask))
    if layer is None:
        # The gain of the observation slots; the mask and context columns are constant for a
        # coordinate (no covariance, no gain) and would only grow the matrix to factorise.
        reach = mask.shape[1]
        gain = jax.vmap(lambda xi, yi: enkf_gain(xi, yi[:, :reach], active), in_axes=(1, 1))(x, y)
        gain = jnp.pad(gain, ((0, 0), (0, 0), (0, y.shape[-1] - reach)))
        return _LocalData(x, y, local_y(y_standard), gain, x, y, **noise)
    layer_x, layer_y, gain = _local_transforms(x, *layer, mask * numbers.layer_weights, windows.observations,
                                               active, y.shape[-1])
    return _LocalData(x, y, local_y(y_standard), gain, layer_x, layer_y, **noise)


def _window_noise_factor(covariance: Array, observations: Array, mask: Array) -> Array:
    """``[n, K, K]``: the Cholesky factor of each window's noise covariance R[O, O] (``covariance``
    ``[m]``, a diagonal, or ``[m, m]``), masked slots decoupled (unit variance) and their rows 0."""
    if covariance.ndim == 1:
        window = jax.vmap(jnp.diag)(covariance[observations])
    else:
        window = covariance[observations[:, :, None], observations[:, None, :]]
    both = mask[:, :, None] * mask[:, None, :]
    eye = jnp.eye(mask.shape[1], dtype=covariance.dtype)
    factor = jnp.linalg.cholesky(jnp.where(both > 0, window, 0.0) + eye * (1.0 - mask)[:, None, :])
    return jnp.where(mask[:, :, None] > 0, factor, 0.0)


def _fresh_slots(key: Array, data: _LocalData, rows: Array, coordinate: Array, y: Array) -> Array:
    """``y[B, C]`` (the local pairs ``rows``, ``coordinate``) with its observation slots drawn
    afresh: h(X)_O plus Gaussian noise of the window's covariance (0 on masked slots)."""
    slots = data.predicted[rows, coordinate]
    noise = jnp.einsum("bkj,bj->bk", data.noise_factor[coordinate], jax.random.normal(key, slots.shape, slots.dtype))
    return y.at[:, :slots.shape[1]].set(slots + noise)


def _location_features(scaling: Standardisation, windows: LocalWindows, mask: Array) -> Array:
    """``[n, 2 (S + K)]``: arcsinh of the mean and log of the spread of each window's state
    coordinates and observations (the ensemble's, in the model's coordinates; 0 on padding and
    missing slots). arcsinh keeps a mean of 100 (an observation x^2) an input of about 5."""
    state = windows.state_valid.astype(scaling.x_mean.dtype)
    x = jnp.concatenate([jnp.arcsinh(scaling.x_mean)[windows.state] * state,
                         jnp.log(scaling.x_scale)[windows.state] * state], axis=-1)
    y = jnp.concatenate([jnp.arcsinh(scaling.y_mean)[windows.observations] * mask,
                         jnp.log(scaling.y_scale)[windows.observations] * mask], axis=-1)
    return jnp.concatenate([x, y], axis=-1)


def _local_transforms(x: Array, predicted: Array, noise_variance: Array, weights: Array, observations: Array,
                      active: Array, conditioning: int):
    """The deterministic layer of every window: ``(m_W + d [N, n, S], mean h(X)_O [N, n, C],
    K [n, S, C])`` from the windows ``x[N, n, S]``, the predicted observations ``predicted[N, m]``,
    their noise variances ``[m]`` and the slots' ``weights[n, K]`` (the taper; 0 on padding and
    missing components: the noise variance divided by it, as in the LETKF), all standardised."""
    num_active = jnp.sum(active, dtype=jnp.int32)
    scale = 1.0 / jnp.sqrt(jnp.maximum(num_active - 1, 1).astype(x.dtype))
    predicted_mean, predicted_anomalies = masked_mean_and_anomalies(predicted, active, num_active)
    inverse_sd = jnp.sqrt(weights / noise_variance[observations])  # [n, K]; 0 on padding, missing

    def one(x_window, slots, weight):
        mean, anomalies = masked_mean_and_anomalies(x_window, active, num_active)  # [S], [N, S]
        whitened = predicted_anomalies[:, slots] * (weight * scale)  # [N, K]
        # The mean weights for the innovations of unit standardised y per slot: w = G diag(1/sd).
        weights, posterior, _ = etkf_transform(whitened, jnp.diag(weight), anomalies)
        gain = scale * anomalies.T @ weights  # [S, K]
        padded = jnp.zeros((gain.shape[0], conditioning), x.dtype).at[:, :gain.shape[1]].set(gain)
        start = jnp.zeros((conditioning,), x.dtype).at[:slots.shape[0]].set(predicted_mean[slots] * (weight > 0))
        return mean + jnp.where(active[:, None], posterior, 0.0), start, padded

    layer_x, start, gain = jax.vmap(one, in_axes=(1, 0, 0), out_axes=(1, 0, 0))(x, observations, inverse_sd)
    return layer_x, jnp.broadcast_to(start, (x.shape[0],) + start.shape), gain


def move_windows(data: _LocalData, transport: Callable | None, use_gain: bool, slots: int, knots: int = 0,
          active: Array | None = None) -> Array:
    """``[N, n]``: each coordinate's own component of the local map applied to every particle's
    window (``transport`` None: the layer alone, the local perturbed or deterministic EnKF).
    ``slots``: the windows' observation slots K, the gain's only non-zero columns (the layer
    reads those alone: over all C columns it was a quarter of the EnKF's step at n = 50).
    ``knots`` > 0 (windows of one state coordinate): T evaluated at that many points spanning
    the ``active`` particles' inputs and interpolated (``tabulated``)."""

    def one_coordinate(x, y_start, y, gain):
        rows = jnp.broadcast_to(y, y_start.shape)
        inputs = transport_input(x, rows[:, :slots], y_start[:, :slots], gain[:, :slots] if use_gain else None)
        if transport is None:
            return inputs[:, 0]
        if knots:
            return tabulated(lambda u: transport(u[:, None], jnp.broadcast_to(y, (knots,) + y.shape))[:, 0],
                             inputs[:, 0], active, knots)
        return transport(inputs, rows)[:, 0]

    return jax.vmap(one_coordinate, in_axes=(1, 1, 0, 0), out_axes=1)(
        data.layer_x if use_gain else data.x, data.layer_y, data.observation, data.gain)


def tabulated(function: Callable, u: Array, active: Array, knots: int) -> Array:
    """``function(u[N])`` of a scalar function, evaluated at ``knots`` evenly spaced points from
    the least to the largest active u and interpolated linearly (constant beyond them, which only
    inactive rows reach). Where T's input is one coordinate and its conditioning is the same for
    every particle (the actual observation and the window's context), T is a function of that
    coordinate alone, and a ReLU network's is piecewise linear: interpolating it is exact between
    its kinks, and costs ``knots`` network evaluations instead of N."""
    low = jnp.min(jnp.where(active, u, jnp.inf))
    span = jnp.maximum(jnp.max(jnp.where(active, u, -jnp.inf)) - low, jnp.finfo(u.dtype).tiny)
    values = function(low + span * jnp.arange(knots, dtype=u.dtype) / (knots - 1))
    position = jnp.clip((u - low) / span * (knots - 1), 0.0, knots - 1)
    left = jnp.clip(jnp.floor(position).astype(jnp.int32), 0, knots - 2)
    return values[left] + (position - left) * (values[left + 1] - values[left])


def _knots(structure: OTStructure, num_particles: int) -> int:
    """Knots of the tabulated map (0: T at every particle, also where N is not larger)."""
    return structure.map_knots if structure.map_knots < num_particles else 0


def layer_inputs(structure: OTStructure, model: StateSpaceModel, particles: Array, scaling: Standardisation):
    """The deterministic layer's standardised ``h(X)[N, m]`` and noise variances ``[m]``; None
    for the perturbed layer (or none)."""
    if not structure.deterministic_layer:
        return None
    predicted, covariance = _gaussian_observations("enkf_layer='deterministic'", model, particles, scaling)
    return predicted, covariance if covariance.ndim == 1 else jnp.diagonal(covariance)


def _gaussian_observations(option: str, model: StateSpaceModel, particles: Array, scaling: Standardisation):
    """Standardised ``h(X)[N, m]`` and noise covariance: ``[m]`` (a diagonal R) or ``[m, m]``."""
    if not model.has_gaussian_observation_noise:
        raise ValueError(f"local_ot({option}) needs a model with additive Gaussian "
                         "observation noise: give model.observation_function and model.observation_noise_cov")
    noise = jnp.asarray(model.observation_noise_cov, particles.dtype)
    scale = scaling.y_scale**2 if noise.ndim == 1 else jnp.outer(scaling.y_scale, scaling.y_scale)
    predicted = scaling.standardise_y(jax.vmap(model.observation_function)(particles))
    return predicted, noise / scale


def local_pairs(numbers: LocalOTSettings, structure: OTStructure, key: Array, log_weights: Array, particles: Array,
                observation: Array, model: StateSpaceModel):
    """``(PriorData, local pairs)`` of a forecast ensemble: inflated, observations simulated,
    standardised, cut into windows, with the layer's inputs (what the shared map trains on and
    moves; the offline trainer's bank holds these of many ensembles)."""
    prior = prior_data(numbers.ot, key, log_weights, particles, observation, model)
    y_standard = jnp.where(prior.observed, prior.scaling.standardise_y(observation), 0.0)
    layer = layer_inputs(structure, model, prior.particles, prior.scaling)
    fresh = None
    if structure.fresh_observations:
        fresh = _gaussian_observations("fresh_observations=True", model, prior.particles, prior.scaling)
    data = local_data(numbers, prior.xs, prior.ys, y_standard, prior.observed, prior.active, layer,
                       prior.scaling if structure.location_context else None, fresh)
    return prior, data


def sample_local_batch(key: Array, structure: OTStructure, data: _LocalData, active_index: Array,
                       num_active: Array, batch_size: int) -> Batch:
    """A mini-batch of ``batch_size`` local pairs: a (particle, coordinate) pair's window and local
    observations, and another particle's window at the same coordinate (the independent copy, with
    the layer's inputs and the coordinate's gain where there is a layer); the observation slots
    drawn afresh with ``structure.fresh_observations``."""
    pair_key, copy_key, coordinate_key, y_key, ybar_key = jax.random.split(key, 5)
    shape = (batch_size,)
    coordinate = jax.random.randint(coordinate_key, shape, 0, data.x.shape[1])
    pair = active_index[jax.random.randint(pair_key, shape, 0, num_active)]
    copy = active_index[jax.random.randint(copy_key, shape, 0, num_active)]
    y, ybar = data.y[pair, coordinate], data.layer_y[copy, coordinate]
    if structure.fresh_observations:
        y = _fresh_slots(y_key, data, pair, coordinate, y)
        if structure.enkf_layer and not structure.deterministic_layer:  # the copy's own y
            ybar = _fresh_slots(ybar_key, data, copy, coordinate, ybar)
    return Batch(data.x[pair, coordinate], y, data.layer_x[copy, coordinate], ybar,
                 data.gain[coordinate] if structure.enkf_layer else None)


@jax.jit(static_argnames=("structure",))
def _apply(numbers, key, state, particles, observation, model, structure):
    """Simulate, standardise, cut windows, train the shared map, transport, check, fall back."""
    settings = numbers.ot
    num, n = particles.shape
    _, window, _ = window_sizes(numbers.windows)
    conditioning = conditioning_size(numbers, structure)
    simulate_key, train_key, check_key, reset_key = jax.random.split(key, 4)
    potential_net, transport_net = networks(structure)

    prior, data = local_pairs(numbers, structure, simulate_key, state.log_weights, particles, observation, model)
    particles, simulated, active, num_active, scaling, observed, xs, ys = prior
    active_index = active_first(active)

    def sample_batch(batch_key):
        return sample_local_batch(batch_key, structure, data, active_index, num_active, structure.batch_size)

    # No training while the filter has lost track: the local EnKF serves.
    training, trace, trend, lost = train(settings, structure, train_key, reset_key, state, prior, observation,
                                         sample_batch, (window, conditioning), cost_from_layer=True)
    params = training.params
    slots = numbers.windows.observations.shape[1]
    moved = move_windows(data, lambda x, y: transport_net.apply(params.transport, x, y), structure.enkf_layer, slots,
                  _knots(structure, num), active)

    checked = active_index[:min(CHECK_ROWS, num)]  # as ot()'s: the first CHECK_ROWS active particles
    z = predictive_check(check_key, model, scaling.restore_x(moved[checked]), observation, active[checked])
    diverged = lost | divergence_test(trace.finite, trace.smoothed_loss, settings.divergence_threshold,
                                      window, moved, active, z, xs)
    fallback = scaling.restore_x(move_windows(data, None, True, slots))
    posterior = use_where(~diverged, scaling.restore_x(moved), fallback)
    posterior = jnp.where(jnp.any(observed), posterior, particles)
    if structure.first_iterations:  # a map used as is has nothing to restart
        fresh = _starting_training(numbers, structure, reset_key, window, particles.dtype)
        training = use_where(diverged, fresh, training)

    # f's spread over the same particles, each at a random coordinate.
    sample = jax.random.randint(jax.random.fold_in(check_key, 1), checked.shape, 0, n)
    potential_values = potential_net.apply(params.potential, data.x[checked, sample], data.y[checked, sample])
    state = LocalOTState(
        log_weights=state.log_weights,
        training=training,
        standardisation=scaling,
        gain=data.gain,
        simulated_observations=simulated,
        num_updates=jnp.where(diverged, 0, state.num_updates + 1),
        diverged=diverged,
        innovation_trend=trend,
    )
    info = OTInfo(
        loss=trace.loss,
        final_loss=finite_or_inf(trace.smoothed_loss),
        diverged=diverged,
        min_hessian_eigenvalue=jnp.array(jnp.inf, particles.dtype),
        concavity_violation=jnp.zeros((), particles.dtype),
        potential_spread=finite_or_inf(jnp.std(potential_values, where=active[checked])),
        predictive_z=finite_or_inf(z),
        innovation_trend=trend,
    )
    return posterior, state, info


def local_ot_transport(numbers: LocalOTSettings, state: LocalOTState, particles: Array, observation: Array,
                       model: StateSpaceModel | None = None, *, structure: OTStructure) -> Array:
    if structure.deterministic_layer and model is None:
        raise ValueError("the deterministic layer's transport needs the model: transport(state, particles, "
                         "observation, model)")
    num, n = state.log_weights.shape[0], state.gain.shape[0]
    m = state.standardisation.y_mean.shape[0]
    if jnp.shape(particles) != (num, n) or jnp.shape(observation) != (m,):
        raise ValueError(f"particles must have shape ({num}, {n}) and observation ({m},), got "
                         f"{jnp.shape(particles)} and {jnp.shape(observation)}")
    return _transport(numbers, state, particles, jnp.asarray(observation, particles.dtype), model,
                      structure=structure)


@jax.jit(static_argnames=("structure",))
def _transport(numbers, state, particles, observation, model, structure):
    _, transport_net = networks(structure)
    scaling = state.standardisation
    observed = jnp.isfinite(observation)
    active = active_mask(state.log_weights)
    data = local_data(numbers, scaling.standardise_x(particles),
                       jnp.where(observed, scaling.standardise_y(state.simulated_observations), 0.0),
                       jnp.where(observed, scaling.standardise_y(observation), 0.0), observed, active,
                       layer_inputs(structure, model, particles, scaling),
                       scaling if structure.location_context else None)
    params = state.training.params.transport
    return scaling.restore_x(move_windows(data, lambda x, y: transport_net.apply(params, x, y), structure.enkf_layer,
                                   numbers.windows.observations.shape[1], _knots(structure, particles.shape[0]),
                                   active))
