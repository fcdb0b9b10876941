"""Distilling an amortised map into a narrower one, for a cheaper step without training ((a)).

A map used as is costs one forward pass of T over the N particles at every step, and at n = 2
and on Lorenz-63 that pass at the width the saddle-point training needs (64) is most of (a)'s
step (``docs/amortised.md``, "Online cost"). The width is what the max-min game needs to find
the map, not what the map needs to be written down: once found, T is a smooth function of
(x, y, context) that a narrower network can fit by plain regression, a problem with none of
the game's oscillation. ``distil_map`` fits a student of ``width`` to a trained map (the
teacher) on the inputs the teacher meets in its filter: T's on the layer's outputs and the
simulated observations of a bank's ensembles (``bank.py``), f's on the joint pairs and on the
teacher's transported points (where the update's J check reads it). The student is an
``AmortisedMap`` like any other: ``amortised_ot`` filters with it, ``save_map`` stores it (its
``info["distilled_from"]`` records the teacher).

Several teachers (trainings of one setting from different seeds) give one student of their
average. Each training of the game ends somewhere in the oscillation around the saddle point, and
the average of two such maps is closer to it than either: at n = 10 on the dynamic example the
offline stage's two candidates distilled into one width-64 map filtered (a) with W1 0.281 where
the kept candidate gave 0.335 (50 truths; ``docs/amortised.md``), at one map's cost a step.
"""

from __future__ import annotations

import time
from functools import partial
from typing import NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np
import optax

from ot_filter.amortised.bank import ForecastBank, bank_batch
from ot_filter.amortised.training import AmortisedMap, map_recipe
from ot_filter.lib.validation import check_int, check_number
from ot_filter.model import StateSpaceModel
from ot_filter.progress import report
from ot_filter.transport.context import conditioning
from ot_filter.transport.saddle import batch_gain, transport_input
from ot_filter.updates.ot import init_training, networks

Array = jax.Array

__all__ = ["DistillationHistory", "distil_map"]


class DistillationHistory(NamedTuple):
    iterations: np.ndarray  # [C] iterations done at the end of each chunk
    transport_error: np.ndarray  # [C] held-out RMS of T_student - T_teacher over the displacement's RMS
    potential_error: np.ndarray  # [C] held-out RMS of f_student - f_teacher over f_teacher's spread
    seconds: float


def distil_map(key: Array, teacher: AmortisedMap | Sequence[AmortisedMap], model: StateSpaceModel, bank: ForecastBank,
               validation: ForecastBank, *, width: int, num_iterations: int = 20_000, batch_size: int = 1024,
               ensembles_per_batch: int = 16, learning_rate: float = 3e-3, chunks: int = 10,
               validation_batches: int = 8) -> tuple[AmortisedMap, DistillationHistory]:
    """A map of networks ``width`` wide fitted to ``teacher``'s f and T by least squares on
    mini-batches of ``bank`` (``bank_batch``: the teacher's own batch construction), Adam with a
    cosine decay from ``learning_rate``, ``num_iterations`` in ``chunks`` compiled chunks with
    the held-out relative errors (``DistillationHistory``) on ``validation`` after each. Every
    other setting of the map (blocks, activation, layer, context and its scaling, the optimiser
    settings a warm start would use) is the teacher's.

    ``teacher`` may be a sequence of maps trained for the same model with the same settings (their
    widths may differ): the student then fits the average of their T's and of their f's, each
    teacher reading the context through its own scaling, and takes the first one's settings."""
    teachers = _teachers(teacher)
    teacher = teachers[0]
    width = check_int("width", width)
    chunks = check_int("chunks", chunks)
    num_iterations = check_int("num_iterations", num_iterations, minimum=chunks)
    batch_size = check_int("batch_size", batch_size, minimum=2)
    ensembles_per_batch = check_int("ensembles_per_batch", ensembles_per_batch)
    if batch_size % ensembles_per_batch or batch_size // ensembles_per_batch < 2:
        raise ValueError(f"batch_size = {batch_size} must be a multiple (>= 2x) of ensembles_per_batch = "
                         f"{ensembles_per_batch}")
    learning_rate = check_number("learning_rate", learning_rate, 0.0, strict_minimum=True)
    config = teacher.config
    n, m = config.state_dim, config.observation_dim
    for name, one in (("bank", bank), ("validation", validation)):
        if one.particles.ndim != 3 or one.particles.shape[2] != n or one.scaling.y_mean.shape[1] != m:
            raise ValueError(f"{name} must be a ForecastBank of the teacher's model (state dimension {n}, "
                             f"observation dimension {m}), got particles of shape {one.particles.shape}")
    student_config = config._replace(width=width)
    settings, _ = map_recipe(config, context_scaling=teacher.context_scaling)
    teacher_structures = tuple(map_recipe(one.config, context_scaling=one.context_scaling)[1] for one in teachers)
    _, structure = map_recipe(student_config, context_scaling=teacher.context_scaling)
    teacher_params = tuple(one.params for one in teachers)
    contexts = _context_conversions(teachers)
    init_key, train_key, validation_key = jax.random.split(key, 3)
    params = init_training(settings, structure, init_key, n, m, bank.particles.dtype).params
    optimizer = optax.adam(optax.cosine_decay_schedule(learning_rate, num_iterations))
    state = (params, optimizer.init(params))
    sampler = partial(bank_batch, sample_observation=model.sample_observation, batch_size=batch_size,
                      ensembles_per_batch=ensembles_per_batch, enkf_layer=config.enkf_layer,
                      context_scaling=teacher.context_scaling)
    per_chunk = num_iterations // chunks
    iterations, transport_error, potential_error = [], [], []
    started = time.perf_counter()
    for chunk in range(chunks):
        state = _fit_chunk(jax.random.fold_in(train_key, chunk), state, teacher_params, contexts, bank, sampler,
                           teacher_structures, structure, optimizer, per_chunk)
        errors = _errors(validation_key, state[0], teacher_params, contexts, validation, sampler, teacher_structures,
                         structure, validation_batches)
        iterations.append((chunk + 1) * per_chunk)
        transport_error.append(float(errors[0]))
        potential_error.append(float(errors[1]))
        report(chunk + 1, chunks)
    seconds = time.perf_counter() - started
    history = DistillationHistory(np.array(iterations), np.array(transport_error), np.array(potential_error),
                                  seconds)
    sources = [{"width": one.config.width, "info": one.info} for one in teachers]
    info = {"distilled_from": sources[0] if len(sources) == 1 else {"width": config.width, "teachers": sources},
            "distillation": {"iterations": int(iterations[-1]), "batch_size": batch_size,
                             "learning_rate": float(learning_rate), "ensembles": int(bank.num_ensembles),
                             "validation_ensembles": int(validation.num_ensembles), "seconds": seconds,
                             "transport_error": transport_error[-1], "potential_error": potential_error[-1]},
            "finite": bool(np.isfinite(transport_error[-1]) and np.isfinite(potential_error[-1]))}
    return AmortisedMap(state[0], teacher.context_scaling, student_config, info), history


def _teachers(teacher) -> tuple[AmortisedMap, ...]:
    """``teacher`` as a non-empty tuple of maps of one model and one setting (widths aside)."""
    teachers = (teacher,) if isinstance(teacher, AmortisedMap) else tuple(teacher) if isinstance(teacher, (list, tuple)) else ()
    wrong = [type(one).__name__ for one in teachers if not isinstance(one, AmortisedMap)]
    if not teachers or wrong:
        raise TypeError(f"teacher must be an AmortisedMap or a non-empty sequence of them, got "
                        f"{type(teacher).__name__}{' of ' + ', '.join(wrong) if wrong else ''}")
    setting = teachers[0].config._replace(width=0)
    for index, one in enumerate(teachers[1:], start=1):
        if one.config._replace(width=0) != setting:
            raise ValueError(f"teacher[{index}] was trained for another model or with other settings than teacher[0] "
                             f"({one.config} against {teachers[0].config}): only the widths may differ")
    return teachers


def _context_conversions(teachers):
    """Per teacher ``(factor, shift)`` taking the first teacher's normalised context to its own
    (``c_k = c * factor + shift``: each training standardised the context on its own bank);
    None without context."""
    first = teachers[0].context_scaling
    if first is None:
        return None
    return tuple((first.scale / one.context_scaling.scale, (first.mean - one.context_scaling.mean) / one.context_scaling.scale)
                 for one in teachers)


def teacher_average(teachers, contexts, batch, teacher_structures):
    """``(inputs, y, T, f)`` of a distillation batch: T's input, what the student conditions on,
    and the teachers' average T at the inputs and f at the joint pairs and the transported points
    (where the update evaluates f), each teacher on its own context scaling (``contexts``)."""
    inputs = transport_input(batch.xbar, batch.y, batch.ybar, batch_gain(batch, teacher_structures[0].enkf_layer))
    y = conditioning(batch.y, batch.context)
    conditions = [y if contexts is None else conditioning(batch.y, batch.context * factor + shift)
                  for factor, shift in (contexts or [(None, None)] * len(teachers))]
    target = sum(networks(structure)[1].apply(params.transport, inputs, on)
                 for params, structure, on in zip(teachers, teacher_structures, conditions)) / len(teachers)
    points = jnp.concatenate([batch.x, target])
    f_target = sum(networks(structure)[0].apply(params.potential, points, jnp.concatenate([on, on]))
                   for params, structure, on in zip(teachers, teacher_structures, conditions)) / len(teachers)
    return inputs, y, target, f_target


def _terms(student, teachers, contexts, batch, teacher_structures, structure):
    """Per-batch ``(T error, displacement, f error, f spread)`` sums of squares (means)."""
    student_f, student_t = networks(structure)
    inputs, y, target, f_target = teacher_average(teachers, contexts, batch, teacher_structures)
    moved = student_t.apply(student.transport, inputs, y)
    f_value = student_f.apply(student.potential, jnp.concatenate([batch.x, target]), jnp.concatenate([y, y]))
    return (jnp.mean(jnp.sum((moved - target) ** 2, axis=-1)), jnp.mean(jnp.sum((target - inputs) ** 2, axis=-1)),
            jnp.mean((f_value - f_target) ** 2), jnp.var(f_target))


@partial(jax.jit, static_argnames=("sampler", "teacher_structures", "structure", "optimizer", "num_iterations"))
def _fit_chunk(key, state, teachers, contexts, bank, sampler, teacher_structures, structure, optimizer, num_iterations):
    def loss(params, batch):
        transport, displacement, potential, spread = _terms(params, teachers, contexts, batch, teacher_structures,
                                                            structure)
        # Each term relative to its scale, so that neither dominates whatever f's units.
        return transport / (displacement + 1e-6) + potential / (spread + 1e-6)

    def step(state, step_key):
        params, opt_state = state
        gradient = jax.grad(loss)(params, sampler(step_key, bank))
        updates, opt_state = optimizer.update(gradient, opt_state, params)
        return (optax.apply_updates(params, updates), opt_state), None

    state, _ = jax.lax.scan(step, state, jax.random.split(key, num_iterations))
    return state


@partial(jax.jit, static_argnames=("sampler", "teacher_structures", "structure", "num_batches"))
def _errors(key, params, teachers, contexts, bank, sampler, teacher_structures, structure, num_batches):
    """Held-out relative RMS errors of T and f (the same batches at every call)."""
    terms = jax.vmap(lambda k: _terms(params, teachers, contexts, sampler(k, bank), teacher_structures, structure))(
        jax.random.split(key, num_batches))
    transport, displacement, potential, spread = (jnp.mean(t) for t in terms)
    return jnp.sqrt(transport / displacement), jnp.sqrt(potential / spread)
