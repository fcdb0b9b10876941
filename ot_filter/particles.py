"""The particle state every filter carries, and the checks and snapshots around it.

``ParticleState(particles[N, n], log_weights[N])`` is the weighted empirical measure
``sum_i exp(log_weights_i) delta_{X^i}``: log-weights normalised over the active particles,
-inf on padding (``updates.base`` describes the padded particle axis), so the active mask is
part of the type (``state.active``, ``state.num_active``). ``run_filter`` and
``continuous.run_fpf`` both carry one (the FPF's weights stay uniform), validate their arguments
with ``check_filter_arguments`` and draw and save particles through the same functions here.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ot_filter.lib.validation import check_finite_array, check_int, is_traced
from ot_filter.lib.weights import active_mask, count_active, uniform_log_weights
from ot_filter.progress import maybe_report

Array = jax.Array

__all__ = [
    "ParticleState",
    "check_filter_arguments",
    "check_num_active",
    "check_progress",
    "initial_particle_state",
    "saved_step_indices",
    "scan_with_snapshots",
]


class ParticleState(NamedTuple):
    """Particles and their normalised log-weights (-inf: padding)."""

    particles: Array  # [N, n]
    log_weights: Array  # [N]

    @property
    def active(self) -> Array:
        """``[N]`` bool, False for padding."""
        return active_mask(self.log_weights)

    @property
    def num_active(self) -> Array:
        """The number of active particles (int32 scalar)."""
        return count_active(self.log_weights)


def check_progress(progress) -> int:
    if isinstance(progress, bool) or not isinstance(progress, (int, np.integer)) or progress < 0:
        raise ValueError(f"progress must be an int >= 0 (report every k steps; 0: off), got {progress!r}")
    return int(progress)


def check_filter_arguments(
    num_particles, save_every, num_steps: int, state_dim: int, initial_particles, progress
) -> tuple[int, int, int]:
    """The checks every filter makes: ``(num_particles, save_every, progress)`` as Python ints,
    ``save_every`` set to 0 when no step would be saved; ``initial_particles`` (if given) must
    be a finite ``[N, n]`` array."""
    if isinstance(num_particles, bool) or not isinstance(num_particles, (int, np.integer)):
        raise TypeError(f"num_particles must be an int, got {type(num_particles).__name__}")
    num_particles = check_int("num_particles", num_particles, minimum=2)
    save_every = check_int("save_every", save_every, minimum=0)
    if initial_particles is not None:
        check_finite_array("initial_particles", initial_particles, (num_particles, state_dim))
    if save_every > num_steps:
        save_every = 0  # no step would be saved
    return num_particles, save_every, check_progress(progress)


def check_num_active(num_active, num_particles: int) -> Array:
    """An int32 scalar; concrete values must lie in [2, num_particles]."""
    dtype = getattr(num_active, "dtype", None)
    if isinstance(num_active, bool) or not (
        isinstance(num_active, (int, np.integer))
        or (dtype is not None and jnp.issubdtype(dtype, jnp.integer) and jnp.ndim(num_active) == 0)
    ):
        raise TypeError(
            f"num_active must be an int or an int scalar array, got {num_active!r}"
        )
    if not is_traced(num_active):
        value = int(num_active)
        if not 2 <= value <= num_particles:
            raise ValueError(
                f"num_active must satisfy 2 <= num_active <= num_particles = {num_particles}, "
                f"got {value}"
            )
    return jnp.asarray(num_active, jnp.int32)


def initial_particle_state(
    key: Array, sample_initial: Callable, num_particles: int, initial_particles: Array | None,
    num_active: Array | None = None,
) -> ParticleState:
    """N draws from ``sample_initial`` (or the given particles) with equal log-weights over the
    first ``num_active`` (all if None) and -inf padding after them."""
    if initial_particles is None:
        particles = jax.vmap(sample_initial)(jax.random.split(key, num_particles))
    else:
        particles = jnp.asarray(initial_particles)
    return ParticleState(particles, uniform_log_weights(particles, num_active))


def saved_step_indices(save_every: int, num_steps: int) -> np.ndarray:
    """The 0-based time indices after which ``scan_with_snapshots`` saves (a NumPy array)."""
    return np.arange(save_every - 1, num_steps, save_every) if save_every else np.zeros(0, int)


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
