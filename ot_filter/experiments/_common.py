"""Helpers shared by the experiment modules: method builders, summary statistics, timing, figures."""

from __future__ import annotations

import os
import re
import time
from functools import partial
from typing import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from ot_filter.model import simulate
from ot_filter.localisation import local_windows, localisation
from ot_filter.updates import (
    SplitLikelihoodInfo, averaged_maps, enkf, flow_matching, letkf, local_etpf, ot, sir, split_likelihood,
)
from ot_filter.updates.local_flow import local_flow
from ot_filter.updates.local_ot import local_ot

METHODS = ("enkf", "sir", "ot")
# Every method an experiment on a model with a geometry can run: the localised ones (``letkf``,
# ``local_ot``, ``local_flow``, ``local_etpf`` and the hybrids that finish with it, ``letkf_etpf`` and
# ``local_ot_etpf``) read ``model.geometry`` at the radius the experiment gives.
LOCAL_METHODS = ("letkf", "local_ot", "local_flow", "local_etpf", "letkf_etpf", "local_ot_etpf")
ALL_METHODS = ("enkf", "letkf", "sir", "ot", "flow_matching", "local_ot", "local_flow", "local_etpf", "letkf_etpf",
               "local_ot_etpf")
# The hybrids (``then_etpf``): an update (the LETKF: ``letkf_etpf``; the localised OT map:
# ``local_ot_etpf``) on l^0.75, the localised ETPF on l^0.25. Chosen for ``letkf_etpf``: on
# Lorenz-96 with y = |x| every 0.2 (16 truths) the powers 0.1-0.35 gave 0.41-0.44 against the
# LETKF's 0.60; 0.5 lost track on one truth and 0.75 on 14 of 16
# (``benchmarks/results/ot_lorenz96/etpf_16/``). ``local_ot_etpf`` takes it untuned (0.424).
ETPF_POWER = 0.25
# ``<method>_avg<K>`` (``ot``, ``flow_matching`` or ``local_ot``, e.g. ``local_ot_avg3``): that method trained K times
# with independent keys, the transported particles averaged (``averaged_maps``); not a default.
AVERAGEABLE = ("ot", "flow_matching", "local_ot")
_AVERAGED = re.compile(r"^(?P<method>[a-z_]+)_avg(?P<count>[1-9][0-9]*)$")


def make_updates(methods: Sequence[str], ot_options: dict | None, ot_defaults: dict | None = None,
                 model=None, radius: float | None = None, state_radius: float = 0.0) -> dict:
    """``{name: update}`` for the named methods; OT gets ``ot_defaults`` updated by ``ot_options``
    (the localised OT update too, but for the global map's smoothing and concavity options:
    ``fresh_observations`` given here is the global map's and the localised one's, whose defaults
    differ, True and False; ``flow_matching`` and ``local_flow`` keep their own defaults).
    ``letkf``, ``local_ot``, ``local_flow`` and ``local_etpf`` need the ``model``
    (its geometry) and a localisation ``radius`` (a step taper for the LETKF and the LETPF, so
    that all three see the same observations). ``ot_avgK`` and ``local_ot_avgK`` are ``ot`` and
    ``local_ot`` trained K times with their own keys, the outputs averaged (``averaged_maps``)."""
    options = dict(ot_defaults or {})
    options.update(ot_options or {})
    local_options = {k: v for k, v in options.items() if k not in ("concavity_points", "prior_smoothing",
                                                                   "concavity_step")}

    def localised(build):
        if model is None or getattr(model, "geometry", None) is None or radius is None:
            raise ValueError("the localised methods need a model with a geometry and a radius")
        return build()

    builders = {
        "enkf": lambda: enkf(),
        "sir": lambda: sir(),
        "ot": lambda: ot(**options),
        # The regression-trained transport keeps its own defaults: the OT options (a max-min
        # game's schedule and networks) are not its.
        "flow_matching": lambda: flow_matching(),
        "letkf": lambda: localised(lambda: letkf(localisation(model.geometry, max(radius, 1e-6), "step"))),
        "local_ot": lambda: localised(lambda: local_ot(local_windows(model.geometry, radius, state_radius),
                                                       **local_options)),
        # Its own defaults, as flow_matching's.
        "local_flow": lambda: localised(lambda: local_flow(local_windows(model.geometry, radius, state_radius))),
        "local_etpf": lambda: localised(lambda: local_etpf(localisation(model.geometry, max(radius, 1e-6), "step"))),
        "letkf_etpf": lambda: localised(lambda: letkf_etpf(localisation(model.geometry, max(radius, 1e-6), "step"))),
        "local_ot_etpf": lambda: localised(lambda: then_etpf(
            local_ot(local_windows(model.geometry, radius, state_radius), **local_options),
            localisation(model.geometry, max(radius, 1e-6), "step"))),
    }
    for name in methods:
        averaged = _AVERAGED.match(name)
        if averaged and averaged["method"] in AVERAGEABLE:
            builders[name] = partial(lambda base, count: averaged_maps(builders[base](), count),
                                     averaged["method"], int(averaged["count"]))
    unknown = [name for name in methods if name not in builders]
    if unknown or not methods:
        raise ValueError(f"methods must be a non-empty subset of {list(builders)} (or ot_avgK, flow_matching_avgK, "
                         f"local_ot_avgK: K trainings averaged), got {list(methods)}")
    return {name: builders[name]() for name in methods}


def methods_present(names) -> list:
    """The method names among ``names`` in ``ALL_METHODS``' order, then the others (``<method>_avgK``)
    in theirs: what a figure or table of a run shows."""
    names = list(names)
    return [m for m in ALL_METHODS if m in names] + [m for m in names if m not in ALL_METHODS and _AVERAGED.match(m)]


def diverged_flags(info):
    """The steps where a training diverged (and its update fell back), from an update's info: its
    ``diverged``, or any of its steps' under ``split_likelihood``; None if no step trains. Any
    leading axes (time, simulations, particle counts) are kept."""
    steps = info.steps if isinstance(info, SplitLikelihoodInfo) else (info,)
    flags = [step.diverged for step in steps if hasattr(step, "diverged")]
    if not flags:
        return None
    return flags[0] if len(flags) == 1 else jnp.any(jnp.stack(flags), axis=0)


def then_etpf(first, local, power=None):
    """The update ``first`` on l^(1 - power), then the LETPF (localisation ``local``) on l^power
    (default ``ETPF_POWER``; may be traced): the first step takes most of the likelihood without
    collapsing, the exact transport corrects what its shape assumptions miss."""
    power = ETPF_POWER if power is None else power
    return split_likelihood([first, local_etpf(local)], [1.0 - power, power])


def letkf_etpf(local, inflation: float = 1.0):
    """``then_etpf`` after the LETKF (``inflation``), both with the localisation ``local``."""
    return then_etpf(letkf(local, inflation), local)


@partial(jax.jit, static_argnums=(2, 3))
def simulate_truths(key, model, num_steps: int, num_simulations: int):
    """``(states[S, T, n], observations[S, T, m])``: independent trajectories of the model.

    Jitted at module level: models built alike are equal as static structure (their numbers are
    traced leaves), so a sweep's cells reuse one compiled program instead of retracing an eager
    vmap for every cell (0.6 s a cell for a small Lorenz-96 sweep).
    """
    return jax.vmap(lambda k: simulate(k, model, num_steps))(jax.random.split(key, num_simulations))


def stats(values) -> dict:
    """Mean, std, standard error, min and max of a sample (JSON-ready floats)."""
    values = np.asarray(values, dtype=np.float64)
    count = values.size
    return {
        "mean": float(values.mean()),
        "std": float(values.std(ddof=1)) if count > 1 else 0.0,
        "stderr": float(values.std(ddof=1) / np.sqrt(count)) if count > 1 else 0.0,
        "min": float(values.min()),
        "max": float(values.max()),
    }


# On a CPU, XLA's LLVM backend at optimisation level 1 instead of its default 2: the OT filters
# compile faster at the same speed (one core: the demo's global filter 21 s -> 15 s, mean of 4;
# the CLI's Lorenz-63 OT run, 2 cores: compile 13.5 s -> 11.2 s, run 60.7 s -> 60.0 s, the same
# MSE). Their time goes to matrix products, which LLVM does not generate.
CPU_COMPILER_OPTIONS = {"xla_backend_optimization_level": 1}


def compile_and_run(function: Callable, *args, shard: bool = True) -> tuple[object, dict]:
    """Jit-compiles ``function`` for ``args``, runs it once; returns its output (as NumPy) and
    ``{"compile_s", "run_s"}`` measured separately.

    With several devices (GPUs, or CPU host devices: ``host_devices_for_cpu_cores``) and
    ``shard``, the leading axis of every argument (independent simulations) is split across them
    with ``jax.sharding``; XLA partitions the vmapped program accordingly. When every argument
    and every output leads with the same simulation count S that the devices do not divide, the
    arguments are padded (the last simulation repeated) to the next multiple and the outputs cut
    back to S: 5 simulations on 2 cores run as 3 + 3 instead of 5 on one.

    On CPU host devices, a program whose LAPACK calls act on matrices larger than
    ``CPU_SHARDED_LAPACK_LIMIT`` runs on one device (``_large_lapack_calls``): with jax 0.10.2 on
    2 cores, two host devices running such calls at once deadlock (measured: batched Cholesky
    of 64 x 64 matrices, SVD of 40 x 40, the EnKF at n = 50 with 3 simulations a device; never
    at 32 x 32 or below).
    """
    devices = jax.devices()
    count, unsharded = None, args
    if shard and len(devices) > 1:
        sizes = {np.shape(a)[0] if np.ndim(a) else None for a in args}
        if len(sizes) == 1 and None not in sizes and next(iter(sizes)) % len(devices):
            count = next(iter(sizes))
            padded = -(-count // len(devices)) * len(devices)
            padded_args = tuple(_repeat_last(a, padded) for a in args)
            outputs = jax.eval_shape(function, *padded_args)
            if all(np.ndim(o) and o.shape[0] == padded for o in jax.tree.leaves(outputs)):
                args = padded_args
            else:
                count = None
        if all(np.ndim(a) and np.shape(a)[0] % len(devices) == 0 for a in args):
            sharding = NamedSharding(Mesh(np.asarray(devices), ("simulations",)), PartitionSpec("simulations"))
            args = tuple(jax.device_put(a, sharding) for a in args)
    start = time.perf_counter()
    lowered = jax.jit(function).lower(*args)
    if args is not unsharded and devices[0].platform == "cpu" and _large_lapack_calls(lowered.as_text()):
        count, args = None, unsharded  # one device (docstring); lowered twice only here
        lowered = jax.jit(function).lower(*args)
    on_cpu = {device.platform for leaf in args for device in _devices_of(leaf)} <= {"cpu"}
    compiled = lowered.compile(CPU_COMPILER_OPTIONS if on_cpu else None)
    compile_s = time.perf_counter() - start
    start = time.perf_counter()
    output = jax.block_until_ready(compiled(*args))
    run_s = time.perf_counter() - start
    if count is not None:
        output = jax.tree.map(lambda leaf: leaf[:count], output)
    return jax.tree.map(np.asarray, output), {"compile_s": compile_s, "run_s": run_s}


def _devices_of(leaf) -> set:
    """The devices an argument lives on (a NumPy array or a scalar: the default device)."""
    return leaf.devices() if isinstance(leaf, jax.Array) else {jax.devices()[0]}


def _repeat_last(array, size: int):
    """``array`` with its last row repeated up to ``size`` rows (padding that is cut away)."""
    return jnp.concatenate([array, jnp.repeat(array[-1:], size - array.shape[0], axis=0)])


# The largest matrix side a LAPACK call may have in a program sharded over CPU host devices.
CPU_SHARDED_LAPACK_LIMIT = 32


def _large_lapack_calls(program: str) -> bool:
    """Whether a program (its StableHLO text) calls LAPACK on a matrix with a side above
    ``CPU_SHARDED_LAPACK_LIMIT`` (the operand types of its ``lapack_*`` custom calls)."""
    for line in program.splitlines():
        if "custom_call @lapack_" in line and "->" in line:
            operands = line.rsplit(":", 1)[-1].split("->")[0]
            for shape in re.findall(r"tensor<((?:\d+x)+)[a-z]", operands):
                sides = [int(d) for d in shape.rstrip("x").split("x")]
                if len(sides) >= 2 and max(sides[-2:]) > CPU_SHARDED_LAPACK_LIMIT:
                    return True
    return False


def host_devices_for_cpu_cores() -> None:
    """Before JAX starts: on a CPU, one single-threaded XLA host device per core, so that
    ``compile_and_run`` spreads independent simulations over the cores. The OT filter's small
    matrix products gain nothing from intra-op threads (one core runs the Lorenz-63 experiment
    faster than two cores with threading); separate devices use the cores fully. Keeps any
    XLA_FLAGS already set."""
    if "xla_force_host_platform_device_count" not in os.environ.get("XLA_FLAGS", ""):
        os.environ["XLA_FLAGS"] = (
            os.environ.get("XLA_FLAGS", "")
            + f" --xla_force_host_platform_device_count={os.cpu_count() or 1}"
            + " --xla_cpu_multi_thread_eigen=false"
        ).strip()


def write_text_atomic(path: str, text: str) -> None:
    """Writes ``text`` to ``path`` via a temporary file and a rename: never a half-written file."""
    tmp = path + ".tmp"
    with open(tmp, "w") as handle:
        handle.write(text)
    os.replace(tmp, path)


def save_figure(fig, out_dir: str, name: str) -> str:
    """Writes ``fig`` as ``out_dir/name`` atomically (temporary file, then rename); closes it."""
    import matplotlib.pyplot as plt

    os.makedirs(out_dir, exist_ok=True)
    path = os.path.join(out_dir, name)
    fig.tight_layout()
    fig.savefig(path + ".tmp.png", dpi=110)
    os.replace(path + ".tmp.png", path)
    plt.close(fig)
    return path
