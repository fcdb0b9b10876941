"""Several trainings of a learned transport map, averaged: ``averaged_maps(update, num_maps)``.

The saddle-point training of an OT map does not settle: from one training key to the next (and
from one checkpoint to the next) the map's output moves by about as much as the map's error
(``docs/ot_at_scale.md``, "Where OT still loses"). Averaging K maps trained with independent keys
on the same particles and observation removes that part of the error, as bagging does for any
noisy estimator: the posterior particles are

    X^i <- (1 / K) sum_k T_k(X^i, y),

the output of the average map, a deterministic map of the prior particles (so ``transport`` gives
it for any other y as well). Its bias is the maps' common error, which averaging keeps; where the
maps disagree on which mode a particle goes to, the average puts it between them, so the gain is
largest where the maps agree on the modes and differ in detail. Measured on the chapter's static
example (N = 1000, W1 per coordinate to the exact posterior, ``benchmarks/averaged_maps.py``):
three trainings take about a fifth to a quarter off the localised and the global maps' W1 and
most of their spread over training keys.

The K trainings run as one ``vmap`` (one compiled program: on a GPU a wider batch, on a CPU about
K times the time). Under ``vmap`` every member runs as many iterations as the one with the largest
budget: in a filter, a member that restarted after a divergence (its first budget again, e.g.
1024) makes the others pay for it too. A member whose training diverged (``info.diverged``: it fell
back, e.g. to the EnKF) is left out of the average; when every member diverged the first member's
fallback is the output (``info.diverged``; ``info.num_averaged`` counts the members averaged, 0
then, and also 0 on a step a filter skips). In a filter each member warm-starts from its own last
training. K = 1 is the member run with the key ``split(key, 1)[0]``, not ``key``.

Only updates that move each particle by a trained map (``ot``, ``local_ot``, ``amortised_ot``:
NamedTuples with ``init``, ``apply`` and ``transport``, whose states and infos carry
``diverged``) can be averaged this way: the average of K EnKF or SIR outputs is not a draw from
anything, and neither is that of maps with the perturbed EnKF layer (``enkf_layer=True``), whose
members read their own simulated observations (the average would shrink those perturbations:
refused; the deterministic layer is a map and is accepted). An ``amortised_ot`` used as is (no
training online) gives the same map K times: averaging it changes nothing.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp

from ot_filter.lib.static import bind, functions_as_pytrees
from ot_filter.lib.validation import check_int

Array = jax.Array

__all__ = ["AveragedMapsInfo", "AveragedMapsState", "AveragedMapsUpdate", "averaged_maps"]


class AveragedMapsState(NamedTuple):
    log_weights: Array  # [N]: the members' (uniform; -inf on padding)
    maps: Any  # the members' states, stacked along a leading axis of length K


class AveragedMapsInfo(NamedTuple):
    maps: Any  # the members' infos, stacked along a leading axis of length K
    diverged: Array  # bool: every member diverged, so the output is the first member's fallback
    num_averaged: Array  # int: the members averaged (those that did not diverge)


class AveragedMapsUpdate(NamedTuple):
    """``BayesUpdate``'s ``init``/``apply``, plus ``transport(state, *args, **kwargs)``: the
    average of the members' ``transport`` (the members that did not diverge at the last apply)."""

    init: Callable[..., AveragedMapsState]
    apply: Callable[..., tuple[Array, AveragedMapsState, AveragedMapsInfo]]
    transport: Callable[..., Array]


def averaged_maps(update, num_maps: int = 3) -> AveragedMapsUpdate:
    """Builds the update that trains ``num_maps`` copies of ``update`` (each with its own key) and
    averages their transported particles (module docstring).

    Args:
      update: a map-based Bayes update (``ot()``, ``local_ot(...)``, ``amortised_ot(...)``): a
        NamedTuple with ``init``, ``apply`` and ``transport``.
      num_maps: K >= 1 (static: the members are one vmapped program).

    Info: ``AveragedMapsInfo(maps, diverged, num_averaged)``: the members' infos stacked, whether
    every member fell back, and how many were averaged.
    """
    num_maps = check_int("num_maps", num_maps)
    missing = [name for name in ("_fields", "init", "apply", "transport") if not hasattr(update, name)]
    if missing:
        raise TypeError(f"update must be a map-based Bayes update (a NamedTuple with init, apply and transport, "
                        f"e.g. ot()); {type(update).__name__} has no {', '.join(missing)}")
    if isinstance(update, AveragedMapsUpdate):
        raise TypeError("update is averaged already: give averaged_maps the map-based update itself")
    structure = getattr(getattr(update.apply, "func", None), "keywords", {}).get("structure")
    if getattr(structure, "enkf_layer", False) and not getattr(structure, "deterministic_layer", False):
        # x + K (y - Y^i) reads each member's own simulated Y^i: the average of K members would
        # average K independent perturbations and shrink the posterior's spread.
        raise ValueError("averaged_maps: a member with the perturbed EnKF layer (enkf_layer=True) cannot be averaged "
                         "(the average shrinks its observation perturbations); use enkf_layer='deterministic' or none")
    member = functions_as_pytrees(update)
    return AveragedMapsUpdate(bind(_init, member, num_maps=num_maps), bind(_apply, member, num_maps=num_maps),
                              bind(_transport, member))


def _diverged(tree, what: str) -> Array:
    if not hasattr(tree, "diverged"):
        raise TypeError(f"averaged_maps: the member's {what} ({type(tree).__name__}) has no 'diverged' field, so a "
                        "fallen-back member could not be left out: average map-based updates only")
    return tree.diverged


def _average(outputs: Array, diverged: Array) -> Array:
    """The mean over the leading axis of ``outputs`` of the members that did not diverge; the
    first member's output when all did."""
    used = jnp.logical_not(diverged)
    count = jnp.sum(used)
    chosen = jnp.where(count > 0, used, jnp.arange(used.shape[0]) == 0)
    chosen = chosen.reshape(chosen.shape + (1,) * (outputs.ndim - 1))
    # where, not a product with 0: a left-out member's output must not reach the sum even if inf
    return jnp.sum(jnp.where(chosen, outputs, 0.0), axis=0) / jnp.maximum(count, 1).astype(outputs.dtype)


def _init(update, key, particles, model=None, *, num_maps):
    maps = jax.vmap(lambda one: update.init(one, particles, model))(jax.random.split(key, num_maps))
    return AveragedMapsState(maps.log_weights[0], maps)


def _apply(update, key, state, particles, observation, model, *, num_maps):
    def member(one, member_state):
        return update.apply(one, member_state._replace(log_weights=state.log_weights), particles, observation, model)

    outputs, maps, infos = jax.vmap(member)(jax.random.split(key, num_maps), state.maps)
    diverged = _diverged(infos, "info")
    posterior = _average(outputs, diverged)
    info = AveragedMapsInfo(infos, jnp.all(diverged), jnp.sum(jnp.logical_not(diverged)))
    return posterior, AveragedMapsState(maps.log_weights[0], maps), info


def _transport(update, state, *args, **kwargs):
    outputs = jax.vmap(lambda member_state: update.transport(member_state, *args, **kwargs))(state.maps)
    return _average(outputs, _diverged(state.maps, "state"))
