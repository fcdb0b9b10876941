"""Localisation: where the state and the observations lie, and how fast correlations decay.

An ensemble of N members spans at most N - 1 directions: with N below the state dimension n,
the sample covariance is rank deficient and its long-range entries are noise. Localisation lets
each part of the state see only nearby observations, so that a few dozen members serve
thousands of unknowns (every operational ensemble system does this).

The description has two parts:

- ``Geometry`` (a model property, ``StateSpaceModel.geometry``): positions of the n state
  coordinates and the m observation components in a d-dimensional domain, each axis periodic
  (a ring, with its period) or not (``period = inf``), and optionally a user metric. Built by
  ``ring(size, observed)`` (Lorenz-96 carries one) or ``points(...)``.
- ``Localisation`` (a tuning choice, given to the update): a ``taper`` (static: 'gaspari_cohn'
  or 'step'), a ``radius`` (traced: ``vmap`` over it runs in one program) and, precomputed on the
  host from the geometry, each state coordinate's neighbouring observations within the taper's
  support at ``max_radius`` (static bound of a traced radius). Built by ``localisation(...)``.

Tapers, with r = distance / radius:

- ``gaspari_cohn``: Gaspari & Cohn's (1999, eq. 4.10) compactly supported fifth-order piecewise
  rational function of half-width c = sqrt(10/3) radius (support 2c = 3.65 radius), the c for
  which it matches the Gaussian exp(-r^2 / 2) to second order at 0: ``radius`` is the Gaussian's
  length scale. DAPPER uses the same convention with the factor rounded to 1.82 (its
  ``loc_rad``), so the radii are interchangeable to 0.3 %.
- ``step``: 1 within ``radius``, 0 beyond.

Local windows (``local_windows``) serve updates that learn ONE map shared by all coordinates
(the localised OT update): each state coordinate's state neighbours and observations within a
radius, in an order that means the same relative position for every coordinate (nearest first,
ties by signed displacement), so that slot k of a window is "the same place" everywhere on a
lattice.

The LETKF uses the neighbour lists (O(n K) work, K the most observations within reach of one
coordinate); the Schur-product EnKF uses dense taper matrices from the positions (O(n m + m^2)
memory: for m up to a few thousand).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ot_filter.lib.validation import check_int, check_number, is_traced

Array = jax.Array

__all__ = [
    "GASPARI_COHN_HALF_WIDTH",
    "Geometry",
    "Localisation",
    "TAPERS",
    "LocalWindows",
    "distances",
    "local_windows",
    "localisation",
    "points",
    "check_localisation",
    "check_localised_analysis",
    "ring",
    "taper_weights",
]

GASPARI_COHN_HALF_WIDTH = math.sqrt(10.0 / 3.0)  # c / radius (see the module docstring)
TAPERS = ("gaspari_cohn", "step")


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Geometry:
    """Positions of the state coordinates and observation components (a pytree; the metric is
    static).

    Attributes:
      state_positions: ``[n, d]``.
      observation_positions: ``[m, d]``.
      period: ``[d]``, the period of each axis (``inf``: not periodic).
      metric: optional ``(a[d], b[d]) -> distance`` replacing the (periodic) Euclidean one.
    """

    state_positions: Array
    observation_positions: Array
    period: Array
    metric: Callable | None = dataclasses.field(default=None, metadata=dict(static=True))


def points(state_positions, observation_positions, period=None, metric: Callable | None = None
           ) -> Geometry:
    """A geometry of general points: ``state_positions[n, d]`` (or ``[n]`` for d = 1),
    ``observation_positions[m, d]``; ``period[d]`` (None or inf entries: not periodic); or a
    ``metric(a, b)`` of two positions (then ``period`` must be None)."""
    state = np.asarray(state_positions, dtype=float)
    observations = np.asarray(observation_positions, dtype=float)
    state = state[:, None] if state.ndim == 1 else state
    observations = observations[:, None] if observations.ndim == 1 else observations
    if state.ndim != 2 or observations.ndim != 2 or state.shape[1] != observations.shape[1]:
        raise ValueError(
            f"state_positions and observation_positions must be [n, d] and [m, d] with the same d, "
            f"got {np.shape(state_positions)} and {np.shape(observation_positions)}"
        )
    if not (np.all(np.isfinite(state)) and np.all(np.isfinite(observations))):
        raise ValueError("state_positions and observation_positions must be finite")
    dim = state.shape[1]
    if metric is not None and period is not None:
        raise ValueError("give period or metric, not both (a metric handles its own periodicity)")
    if period is None:
        period = np.full(dim, np.inf)
    else:
        period = np.asarray(period, dtype=float)
        if period.shape not in ((), (1,), (dim,)):
            raise ValueError(f"period must be a number or have shape ({dim},), got {period.shape}")
        period = np.broadcast_to(period, (dim,)).copy()
    if np.any(period <= 0):
        raise ValueError(f"period must be positive (inf: not periodic), got {period}")
    return Geometry(jnp.asarray(state), jnp.asarray(observations), jnp.asarray(period), metric)


def ring(size: int, observed=None, spacing: float = 1.0) -> Geometry:
    """The periodic 1-D lattice of Lorenz-96: state coordinate i at i * spacing on a ring of
    length size * spacing, observation k at the position of the state coordinate it observes
    (``observed[k]``; None: all)."""
    size = check_int("size", size, minimum=1)
    observed = np.arange(size) if observed is None else np.asarray(observed, dtype=int)
    if observed.ndim != 1 or observed.min(initial=0) < 0 or observed.max(initial=0) >= size:
        raise ValueError(f"observed must be indices in [0, {size}), got {observed!r}")
    positions = spacing * np.arange(size, dtype=float)
    return points(positions, positions[observed], period=size * spacing)


def distances(geometry: Geometry, a: Array, b: Array) -> Array:
    """Pairwise distances ``[p, q]`` between positions ``a[p, d]`` and ``b[q, d]``."""
    if geometry.metric is not None:
        return jax.vmap(lambda x: jax.vmap(lambda z: geometry.metric(x, z))(b))(a)
    gaps = jnp.abs(a[:, None, :] - b[None, :, :])
    period = jnp.asarray(geometry.period, gaps.dtype)
    wrapped = jnp.mod(gaps, jnp.where(jnp.isfinite(period), period, 1.0))  # positions anywhere
    gaps = jnp.where(jnp.isfinite(period), jnp.minimum(wrapped, period - wrapped), gaps)
    return jnp.sqrt(jnp.sum(gaps**2, axis=-1))


def taper_weights(distance: Array, radius, taper: str) -> Array:
    """The taper at ``distance`` (any shape; ``inf`` gives 0) for a length scale ``radius``."""
    if taper == "step":
        return jnp.where(distance <= radius, 1.0, 0.0).astype(jnp.result_type(distance, float))
    if taper != "gaspari_cohn":
        raise ValueError(f"taper must be one of {TAPERS}, got {taper!r}")
    # inf (padding) is replaced before the division, so that the gradient in radius is finite.
    r = jnp.where(jnp.isfinite(distance), distance, 0.0) / (GASPARI_COHN_HALF_WIDTH * radius)
    r = jnp.where(jnp.isfinite(distance), r, 2.0)  # distance / c, support r < 2
    inner = (((-0.25 * r + 0.5) * r + 0.625) * r - 5.0 / 3.0) * r**2 + 1.0
    outer = ((((r / 12.0 - 0.5) * r + 0.625) * r + 5.0 / 3.0) * r - 5.0) * r + 4.0 - 2.0 / (
        3.0 * jnp.maximum(r, 1.0))
    # clipped: the outer polynomial rounds to -1e-7 next to r = 2
    return jnp.clip(jnp.where(r <= 1.0, inner, jnp.where(r < 2.0, outer, 0.0)), 0.0, 1.0)


def taper_support(radius: float, taper: str) -> float:
    """Distance beyond which the taper is 0."""
    return 2.0 * GASPARI_COHN_HALF_WIDTH * radius if taper == "gaspari_cohn" else radius


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Localisation:
    """A taper, its traced radius and each state coordinate's neighbouring observations.

    Attributes:
      geometry: the ``Geometry`` the lists were built from (used by the Schur-product EnKF).
      radius: the taper's length scale (traced).
      neighbours: ``[n, K]`` int, indices of the observations within the taper's support at
        ``max_radius`` of each state coordinate; padded with 0.
      neighbour_distances: ``[n, K]`` their distances (``inf`` on padding: taper 0).
      taper: 'gaspari_cohn' or 'step' (static).
    """

    geometry: Geometry
    radius: Array
    neighbours: Array
    neighbour_distances: Array
    taper: str = dataclasses.field(default="gaspari_cohn", metadata=dict(static=True))

    def weights(self) -> Array:
        """``[n, K]`` taper weights of each coordinate's neighbours (0 on padding)."""
        return taper_weights(self.neighbour_distances, self.radius, self.taper)


def localisation(geometry: Geometry, radius, taper: str = "gaspari_cohn", max_radius=None
                 ) -> Localisation:
    """Builds a ``Localisation`` from a model's geometry (``model.geometry``).

    Args:
      geometry: a concrete ``Geometry`` (the neighbour lists are computed here, on the host).
      radius: the taper's length scale (> 0); may be traced, e.g. vmapped over in a tuning grid,
        then ``max_radius`` must be given.
      taper: 'gaspari_cohn' (default, DAPPER's 'GC') or 'step'.
      max_radius: the largest radius the lists must serve (a Python number); default ``radius``.
        A traced radius above it loses the observations beyond ``max_radius``'s support.
    """
    if not isinstance(geometry, Geometry):
        raise TypeError(f"geometry must be a localisation.Geometry (e.g. model.geometry), got "
                        f"{type(geometry).__name__}")
    if any(is_traced(leaf) for leaf in jax.tree.leaves(geometry)):
        raise ValueError("localisation() needs a concrete geometry (its neighbour lists are built "
                         "on the host): build it outside jit, or close over the model instead of "
                         "passing it as a traced argument")
    if taper not in TAPERS:
        raise ValueError(f"taper must be one of {TAPERS}, got {taper!r}")
    radius = check_number("radius", radius, minimum=0.0, strict_minimum=True)
    if max_radius is None:
        if is_traced(radius):
            raise ValueError("a traced radius needs max_radius (a Python number): the neighbour "
                             "lists are built for it on the host")
        max_radius = radius
    max_radius = check_number("max_radius", max_radius, minimum=0.0, strict_minimum=True)
    if not is_traced(radius) and radius > max_radius:
        raise ValueError(f"radius = {radius} exceeds max_radius = {max_radius}")
    # Host work on the concrete geometry, also when called inside a jit or vmap trace (a
    # tuning grid over a traced radius).
    with jax.ensure_compile_time_eval():
        neighbours, neighbour_distances = _neighbour_lists(geometry, taper_support(max_radius, taper))
    return Localisation(geometry, radius, jnp.asarray(neighbours),
                        jnp.asarray(neighbour_distances), taper)


def check_localisation(localisation) -> Localisation:
    """A localised update's ``localisation`` argument, at build time."""
    if not isinstance(localisation, Localisation):
        raise TypeError(f"localisation must be built by ot_filter.localisation(...), got "
                        f"{type(localisation).__name__}")
    return localisation


def check_localised_analysis(name: str, localisation: Localisation, model, n: int, m: int) -> None:
    """What a localised analysis of ``n`` state coordinates and ``m`` observation components
    (``name``: the update) needs: a model with additive Gaussian noise, and a localisation built
    from a geometry of these sizes."""
    if not model.has_gaussian_observation_noise:
        raise ValueError(f"{name} needs a model with additive Gaussian observation noise: give "
                         "model.observation_function and model.observation_noise_cov")
    if localisation.neighbours.shape[0] != n:
        raise ValueError(f"the localisation has {localisation.neighbours.shape[0]} state "
                         f"coordinates, the particles {n}: build it from this model's geometry")
    if localisation.geometry.observation_positions.shape[0] != m:
        raise ValueError(f"the localisation has {localisation.geometry.observation_positions.shape[0]} "
                         f"observation positions, the observation {m} components")


def _neighbour_lists(geometry: Geometry, cutoff: float, chunk: int = 512):
    """``(indices [n, K], distances [n, K])`` of the observations within ``cutoff`` of each
    state coordinate, nearest first, padded with index 0 at distance inf (K >= 1).

    Chunks of state coordinates bound the memory at ``chunk * m`` distances (n = m = 40,000:
    1.6e9 pairs, about 4 s on one core)."""
    state = jnp.asarray(geometry.state_positions)
    observations = jnp.asarray(geometry.observation_positions)
    compute = jax.jit(lambda a: distances(geometry, a, observations))
    lists = []  # per chunk: (row, column, distance) of the pairs within reach, nearest first
    for start in range(0, state.shape[0], chunk):
        block = np.asarray(compute(state[start:start + chunk]), dtype=np.float64)
        row, column = np.nonzero(block <= cutoff)
        distance = block[row, column]
        order = np.lexsort((column, distance, row))
        lists.append((row[order], column[order], distance[order], block.shape[0]))
    width = max([1] + [int(np.bincount(row).max()) for row, _, _, _ in lists if row.size])
    indices, values = [], []
    for row, column, distance, size in lists:
        counts = np.bincount(row, minlength=size)
        slot = np.arange(row.size) - np.repeat(np.cumsum(counts) - counts, counts)
        block_indices = np.zeros((size, width), np.int32)
        block_values = np.full((size, width), np.inf)
        block_indices[row, slot] = column
        block_values[row, slot] = distance
        indices.append(block_indices)
        values.append(block_values)
    return np.concatenate(indices), np.concatenate(values)


class LocalWindows(NamedTuple):
    """Each state coordinate's local window (host-built, concrete arrays).

    Attributes:
      state: ``[n, S]`` int, the state coordinates within ``state_radius``, the coordinate itself
        first; padded with its own index.
      state_valid: ``[n, S]`` bool, False on padding.
      observations: ``[n, K]`` int, the observation components within ``radius``; padded with 0.
      observations_valid: ``[n, K]`` bool, False on padding.
      observation_distances: ``[n, K]`` the observations' distances from the coordinate (``inf``
        on padding): what a taper within the window reads.
      radius: the windows' observation radius (a 0-d array).
    """

    state: Array
    state_valid: Array
    observations: Array
    observations_valid: Array
    observation_distances: Array
    radius: Array


def local_windows(geometry: Geometry, radius: float, state_radius: float = 0.0) -> LocalWindows:
    """The windows of every state coordinate: observations within ``radius`` and state coordinates
    within ``state_radius`` (distances of ``geometry``; both static Python numbers, >= 0).

    Order within a window: distance, then (the coordinate itself first) the signed displacement
    (wrapped into [-period/2, period/2) on periodic axes), then the index; with a user metric,
    distance then index. On a lattice every coordinate's slot k then sits at the same offset.
    """
    if not isinstance(geometry, Geometry):
        raise TypeError(f"geometry must be a localisation.Geometry (e.g. model.geometry), got "
                        f"{type(geometry).__name__}")
    radius = float(check_number("radius", radius, minimum=0.0))
    state_radius = float(check_number("state_radius", state_radius, minimum=0.0))
    with jax.ensure_compile_time_eval():
        state = np.asarray(geometry.state_positions, np.float64)
        observations = np.asarray(geometry.observation_positions, np.float64)
        state_index, state_valid, _ = _ordered_window(geometry, state, state, state_radius, self_first=True)
        obs_index, obs_valid, obs_distance = _ordered_window(geometry, state, observations, radius, self_first=False)
    return LocalWindows(jnp.asarray(state_index), jnp.asarray(state_valid), jnp.asarray(obs_index),
                        jnp.asarray(obs_valid), jnp.asarray(obs_distance), jnp.asarray(radius))


def _ordered_window(geometry, centres, targets, cutoff, self_first, chunk: int = 512):
    """``(indices [p, K], valid [p, K], distances [p, K])`` of the targets within ``cutoff`` of
    each centre, in the order of ``local_windows``; padding repeats the centre's own index (state)
    or 0, at distance inf."""
    compute = jax.jit(lambda a: distances(geometry, a, jnp.asarray(targets)))
    period = np.asarray(geometry.period, np.float64)
    rows = []
    for start in range(0, centres.shape[0], chunk):
        block = np.asarray(compute(jnp.asarray(centres[start:start + chunk])), np.float64)
        # Round so that lattice ties compare equal despite float noise in the positions.
        block = np.round(block, 9)
        for local, row in enumerate(block):
            centre = start + local
            found = np.nonzero(row <= cutoff + 1e-9)[0]
            keys = [found]
            if geometry.metric is None:
                shift = targets[found] - centres[centre]
                periodic = np.isfinite(period)
                finite_period = np.where(periodic, period, 1.0)
                wrapped = np.mod(shift + finite_period / 2, finite_period) - finite_period / 2
                shift = np.round(np.where(periodic, wrapped, shift), 9)
                keys += [shift[:, axis] for axis in reversed(range(shift.shape[1]))]
            keys.append(found != centre if self_first else np.zeros(found.size, bool))
            keys.append(row[found])
            order = np.lexsort(keys)
            rows.append((found[order], row[found][order]))
    width = max(1, max(len(row) for row, _ in rows))
    indices = np.zeros((len(rows), width), np.int32)
    valid = np.zeros((len(rows), width), bool)
    distance = np.full((len(rows), width), np.inf)
    for centre, (row, gap) in enumerate(rows):
        indices[centre, :] = centre if self_first else 0
        indices[centre, :len(row)] = row
        valid[centre, :len(row)] = True
        distance[centre, :len(row)] = gap
    return indices, valid, distance
