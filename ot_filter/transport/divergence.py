"""The OT update's divergence tests: when a trained map must not be used.

Divergence without NaN is the common failure of the saddle point (f's scale grows and J climbs
long before anything overflows), so the loss LEVEL is tested, not only finiteness. A step
diverged when any of these holds:

- a non-finite loss, parameters or optimiser state (``saddle.TrainingTrace.finite``);
- an exploding smoothed loss, |J| > ``threshold * n`` in standardised units (a converged J is at
  most about 2n);
- transported particles that are non-finite, spread more than ``MAX_POSTERIOR_SPREAD`` prior
  standard deviations, or any of them further from the prior mean, in some coordinate, than
  both ``MAX_TRANSPORT_DISTANCE`` prior standard deviations and its own prior position plus
  ``TRANSPORT_MARGIN`` (a map extrapolating wildly for a few particles: a spread test averages
  them away, and the dynamics may overflow from them: a Lorenz-96 state at 8 attractor standard
  deviations overflows within one step). Per particle because a Bayes update moves particles
  within the prior's reach, and a Lorenz-63 forecast ensemble has particles 8 stds out: an
  absolute bound alone declared 14 of 40 updates diverged there. (Against the prior's furthest
  particle instead, outliers ratcheted outwards by the margin at every update, and a Lorenz-96
  OT filter reached 36 and overflowed);
- the observation more than ``MAX_PREDICTIVE_Z`` standard deviations from the observations
  simulated at the transported particles (a tight ensemble parked in the wrong place: a loss and
  spread that look healthy);
- a filter losing track (``innovation_trend``): each update sees the observation against the
  observations simulated at its PRIOR particles, the forecast of the last analyses. The
  normalised innovation, mean over observed components of (y - mean Y)^2 / var Y, is about 1
  for a filter that tracks (the simulated Y carry the observation noise) and grows as the
  ensemble drifts off the truth while staying tight, and falls as it spreads far wider than its
  errors (an update that inflates instead of assimilating: on Lorenz-96 the global OT filter's
  spread grew to three times the attractor's before the states overflowed, with the average at
  0.2-0.3). Its exponential moving average over updates (``TREND_SMOOTHING``) above a threshold,
  or below ``MIN_INNOVATION_TREND``, is a trend, not one unlucky step: the update falls back to
  the EnKF until the average is back in range, before the states overflow. The lower bound
  applies only where chance cannot reach it: with m observed components the average of a
  tracking filter has std about sqrt(2 / m * (1 - s) / (1 + s)) (s = ``TREND_SMOOTHING``), 0.33
  at m = 2, so the bound is lowered to ``LOW_TREND_SIGMAS`` such stds below 1 (below 0 for
  m <= 4: off). A fixed bound of 0.3 fired on a tracking Lorenz-63 filter (m = 2) in 1 of 10
  simulations, each time restarting the networks.

A map used without training (an amortised update, no online iterations) has no loss to watch,
and fails differently: on a prior unlike its training ensembles it transports without
conditioning. An amortised Lorenz-63 map, run with inflation 1.05 that it was not trained with,
kept 0.86-1.0 of the prior's spread at the updates looked at (steps 300-428), where a linear
update would have kept about 0.4-0.7; the ensemble widened through the dynamics, by up to 10x
a step at the end, with z, the trend and J all in range, until the squared error reached 1e13
(NaN in other simulations). Its update therefore also fails when the transported spread of
some coordinate exceeds ``MAX_SPREAD_OVER_ENKF`` times the EnKF fallback's on the same prior
(``wider_than_enkf``): with it that run stayed bounded (14 of 500 steps fell back). A Bayes
posterior wider than the linear update's by that much needs an observation far in the tails of
its prior predictive.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ot_filter.lib.ensemble import masked_mean_and_std
from ot_filter.model import StateSpaceModel, simulate_observations

Array = jax.Array

__all__ = [
    "CHECK_ROWS",
    "MAX_POSTERIOR_SPREAD",
    "MAX_PREDICTIVE_Z",
    "MAX_SPREAD_OVER_ENKF",
    "MAX_TRANSPORT_DISTANCE",
    "LOW_TREND_SIGMAS",
    "MIN_INNOVATION_TREND",
    "TRANSPORT_MARGIN",
    "TREND_SMOOTHING",
    "lost_track",
    "diverged",
    "innovation_trend",
    "predictive_z",
    "wider_than_enkf",
]

# Transported particles spreading more than this many prior standard deviations mean divergence.
MAX_POSTERIOR_SPREAD = 10.0
# The observation more than this many posterior-predictive standard deviations from the
# posterior-predictive mean means a misplaced ensemble (a correct posterior gives a few at most).
MAX_PREDICTIVE_Z = 10.0
# Particles (the first active ones: particles are exchangeable) at which the global OT update
# checks its map's J and simulates the posterior predictive. Both tests have wide margins: z's sampling
# error is then about 0.13 + 9 % of z against a threshold of 10 that a correct posterior stays
# far below, and J's about 0.2 against 10 n. More rows would cost a map used without training
# (an amortised update) up to twice as much again (measured: 3.8 times the EnKF's step with 64
# rows, 5.3 with 256, at n = 2).
CHECK_ROWS = 64
# A transported particle further than this many prior standard deviations from the prior mean
# means divergence (a Bayes update moves particles within the prior's reach).
MAX_TRANSPORT_DISTANCE = 6.0
# ... and further out than the particle's own prior position plus this many prior stds.
TRANSPORT_MARGIN = 2.0
# A map used without training whose transported spread exceeds this many times the EnKF
# fallback's, in some coordinate, has not conditioned on the observation (module docstring).
MAX_SPREAD_OVER_ENKF = 3.0
# Weight of the past in the moving average of the normalised innovation (about 5 updates).
TREND_SMOOTHING = 0.8
# Below this the ensemble's predicted innovation variance has been, on average over about 5
# updates, twice the realised one: not a Bayes update (a tracking filter stays near 1). At 0.3 a
# Lorenz-96 global OT filter (m = 40) sat at 0.4-0.5 with its spread growing and overflowed.
MIN_INNOVATION_TREND = 0.5
# ... and at least this many chance standard deviations below 1 (see the module docstring).
LOW_TREND_SIGMAS = 4.0


def predictive_z(key: Array, model: StateSpaceModel, particles: Array, observation: Array,
                 active: Array) -> Array:
    """max over coordinates of |y - mean Y'| / std Y', with Y' simulated at ``particles[N, n]``
    by ``simulate_observations`` (non-finite particles replaced by 0 for the simulation; the
    active rows only; over the observed coordinates, NaN ones being missing)."""
    safe = jnp.where(jnp.isfinite(particles), particles, 0.0)
    predicted = simulate_observations(key, model, safe)
    mean, std = masked_mean_and_std(predicted, active)
    z = jnp.abs(observation - mean) / (std + 1e-12)
    return jnp.max(jnp.where(jnp.isfinite(observation), z, 0.0))


def diverged(trace_finite: Array, smoothed_loss: Array, threshold, n: int, moved_standard: Array,
             active: Array, z: Array, prior_standard: Array) -> Array:
    """The divergence test above (bool scalar); ``moved_standard[N, n]`` are the transported
    particles and ``prior_standard[N, n]`` the same particles before, in standardised coordinates."""
    _, spread = masked_mean_and_std(moved_standard, active)
    reach = jnp.maximum(MAX_TRANSPORT_DISTANCE, jnp.abs(prior_standard) + TRANSPORT_MARGIN)
    return (
        ~trace_finite
        | ~(jnp.abs(smoothed_loss) <= threshold * n)
        | ~jnp.all(jnp.isfinite(moved_standard) | ~active[:, None])
        | ~(jnp.max(spread) <= MAX_POSTERIOR_SPREAD)
        | ~jnp.all(jnp.where(active[:, None], jnp.abs(moved_standard), 0.0) <= reach)
        | ~(z <= MAX_PREDICTIVE_Z)
    )


def wider_than_enkf(moved: Array, enkf_particles: Array, active: Array) -> Array:
    """True when some coordinate of the transported ``moved[N, n]`` spreads more than
    ``MAX_SPREAD_OVER_ENKF`` times the EnKF's ``enkf_particles[N, n]`` (active rows, the same
    coordinates)."""
    _, spread = masked_mean_and_std(moved, active)
    _, enkf_spread = masked_mean_and_std(enkf_particles, active)
    return ~jnp.all(spread <= MAX_SPREAD_OVER_ENKF * enkf_spread)


def innovation_trend(previous: Array, simulated: Array, observation: Array, active: Array) -> Array:
    """The moving average of the normalised innovation after this update: ``previous`` the
    average so far (an update's state starts it at 1, a tracking filter's value),
    ``simulated[N, m]`` the observations simulated
    at the prior particles, NaN components of ``observation`` missing (an update with none
    observed leaves the average)."""
    mean, std = masked_mean_and_std(simulated, active)
    observed = jnp.isfinite(observation)
    ratio = jnp.where(observed, (observation - mean) ** 2 / (std**2 + 1e-12), 0.0)
    count = jnp.sum(observed)
    value = jnp.sum(ratio) / jnp.maximum(count, 1)
    value = jnp.where(jnp.isfinite(value), value, jnp.inf)
    updated = TREND_SMOOTHING * previous + (1 - TREND_SMOOTHING) * value
    return jnp.where(count > 0, updated, previous)


def lost_track(trend: Array, threshold, num_observed: Array) -> Array:
    """The filter lost track: the innovation trend above ``threshold`` (an ensemble too tight
    for its errors) or below ``MIN_INNOVATION_TREND`` (far too wide), that lower bound lowered
    where ``num_observed`` components leave the average too noisy to tell (module docstring)."""
    count = jnp.maximum(jnp.asarray(num_observed, trend.dtype), 1.0)
    chance = jnp.sqrt(2.0 / count * (1 - TREND_SMOOTHING) / (1 + TREND_SMOOTHING))
    floor = jnp.minimum(MIN_INNOVATION_TREND, 1.0 - LOW_TREND_SIGMAS * chance)
    return ~((trend <= threshold) & (trend >= floor))
