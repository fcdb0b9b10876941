"""Functions run at the same time in worker processes of their own, one CPU core each.

``start(jobs)`` launches ``{label: ("module:function", kwargs)}`` as
``python -m ot_filter.experiments.processes IN OUT`` processes and returns at once; the caller
works meanwhile and collects the return values with ``Started.results()``. Arguments and return
values travel pickled, so they are NumPy arrays and plain data (a PRNG key as its
``jax.random.key_data``). Each worker's JAX has one single-threaded CPU device (the CLI's setting
per core, ``_common.host_devices_for_cpu_cores``), the caller's precision (x64 or not) and
compilation cache, and this copy of ``ot_filter``. Workers run in sessions of their own, so a
Ctrl-C at the terminal reaches the caller only (which stops them, or lets them finish).

Each worker is pinned to one core of the caller's (``core_for``): XLA's CPU runtime keeps
threads besides the single-threaded device, and two unpinned workers on two cores slowed each
other down. Measured on this project's 2-core machine (AMD EPYC, one n = 10 offline training
chunk of 700 iterations, ``--xla_cpu_multi_thread_eigen=false``): 9.8 s alone, 14.0 s each with
two workers at once unpinned, 8.9 s each with two at once pinned to a core each.

Processes, not threads: two programs run at once from two threads of one process hung in XLA's
CPU runtime (two offline maps trained at n = 10: three tries of three); processes share nothing.
Workers compute on the CPU (``JAX_PLATFORMS=cpu``): on an accelerator each would start a JAX of
its own and claim the device's memory.
"""

from __future__ import annotations

import importlib
import os
import pickle
import signal
import subprocess
import sys
import tempfile
import time
from typing import NamedTuple


def available_cores() -> int:
    """The cores this process may run on (``taskset`` respected where the OS tells)."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


def core_for(index: int, cores: list[int] | None = None) -> int | None:
    """The core worker ``index`` is pinned to: the caller's cores (``cores``, default its
    affinity) taken from the last, round-robin (the caller, unpinned, keeps the first for the
    work it does meanwhile); None where the OS cannot pin."""
    if cores is None:
        if not hasattr(os, "sched_getaffinity"):
            return None
        cores = sorted(os.sched_getaffinity(0))
    return cores[-1 - index % len(cores)]


def worker_environment(environ=os.environ) -> dict:
    """``environ`` with XLA_FLAGS for one single-threaded host device (the parent's other flags,
    such as its compiler options, kept)."""
    flags = [flag for flag in environ.get("XLA_FLAGS", "").split()
             if flag.startswith("--")
             and not flag.startswith(("--xla_force_host_platform_device_count", "--xla_cpu_multi_thread_eigen"))]
    return dict(environ, XLA_FLAGS=" ".join(flags + ["--xla_cpu_multi_thread_eigen=false"]), JAX_PLATFORMS="cpu")


def _caller_settings(environment: dict) -> dict:
    """``environment`` with the caller's JAX precision and compilation cache (set with
    ``jax.config``, which a child process does not inherit) and this ``ot_filter`` first on the
    path."""
    jax = sys.modules.get("jax")
    if jax is not None:
        environment["JAX_ENABLE_X64"] = "1" if jax.config.jax_enable_x64 else "0"
        if jax.config.jax_compilation_cache_dir:
            environment["JAX_COMPILATION_CACHE_DIR"] = jax.config.jax_compilation_cache_dir
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    environment["PYTHONPATH"] = os.pathsep.join(filter(None, [root, environment.get("PYTHONPATH")]))
    return environment


class Started(NamedTuple):
    """Worker processes under way: ``{label: (process, log file, result path)}`` and their
    scratch directory."""

    running: dict
    scratch: tempfile.TemporaryDirectory

    def results(self) -> dict:
        """Waits for every worker; ``{label: return value}``. A failed worker raises
        ``RuntimeError`` with the end of its output, and the others are stopped at once."""
        try:
            failed, waiting = {}, dict(self.running)
            while waiting and not failed:
                for label, (process, log, _) in list(waiting.items()):
                    if process.poll() is None:
                        continue
                    del waiting[label]
                    if process.returncode != 0:
                        log.flush()
                        with open(log.name, errors="replace") as handle:
                            failed[label] = handle.read()[-2000:]
                time.sleep(0.05)
            values = {}
            if not failed:
                for label, (_, _, result) in self.running.items():
                    with open(result, "rb") as handle:
                        values[label] = pickle.load(handle)
        finally:
            self.stop()
        if failed:
            raise RuntimeError("worker processes failed: "
                               + "; ".join(f"{label}: {text}" for label, text in failed.items()))
        return values

    def stop(self) -> None:
        """Kills the workers still running (with whatever they started) and removes the
        scratch directory."""
        for process, log, _ in self.running.values():
            if process.poll() is None:
                try:
                    os.killpg(process.pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
                process.wait()
            log.close()
        self.scratch.cleanup()


def start(jobs: dict) -> Started:
    """Launches every ``{label: ("module:function", kwargs)}`` job in a worker process."""
    for label, (target, _) in jobs.items():
        if not label.isidentifier():
            raise ValueError(f"job label {label!r} must be an identifier (it names the worker's files)")
        if ":" not in target:
            raise ValueError(f"job {label!r}: target {target!r} is not 'module:function'")
    scratch = tempfile.TemporaryDirectory(prefix="ot_filter_workers_")
    environment = _caller_settings(worker_environment())
    running = {}
    try:
        for index, (label, (target, kwargs)) in enumerate(jobs.items()):
            arguments = os.path.join(scratch.name, f"{label}.in.pickle")
            result = os.path.join(scratch.name, f"{label}.out.pickle")
            with open(arguments, "wb") as handle:
                pickle.dump((target, kwargs), handle)
            log = open(os.path.join(scratch.name, f"{label}.log"), "w")
            try:
                # -P: the working directory does not go first on the path (a checkout there would
                # shadow the caller's installed ot_filter); PYTHONPATH puts the caller's first.
                safe_path = ["-P"] if sys.version_info >= (3, 11) else []
                process = subprocess.Popen([sys.executable, *safe_path, "-m", __name__, arguments, result],
                                           env=environment,
                                           stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
            except BaseException:
                log.close()
                raise
            running[label] = (process, log, result)
            core = core_for(index)
            if core is not None:  # the worker has just been exec'ed: its threads are yet to come, and inherit this
                try:
                    os.sched_setaffinity(process.pid, {core})
                except OSError:  # it has already exited (it failed at start; results() reports why)
                    pass
    except BaseException:
        Started(running, scratch).stop()
        raise
    return Started(running, scratch)


def run(jobs: dict) -> dict:
    """``start(jobs).results()``: every job at once, waited for."""
    return start(jobs).results()


def _jax_settings() -> dict:
    """What a worker's JAX runs with (a diagnostic, which the tests use)."""
    import jax

    import ot_filter

    return {"x64": bool(jax.config.jax_enable_x64), "cache": jax.config.jax_compilation_cache_dir,
            "backend": jax.default_backend(), "package": os.path.dirname(ot_filter.__file__)}


def _cores() -> list[int]:
    """The cores this process may run on (a diagnostic, which the tests use)."""
    return sorted(os.sched_getaffinity(0))


def main(arguments: str, result: str) -> None:
    with open(arguments, "rb") as handle:
        target, kwargs = pickle.load(handle)
    module, function = target.split(":")
    value = getattr(importlib.import_module(module), function)(**kwargs)
    with open(result + ".partial", "wb") as handle:
        pickle.dump(value, handle)
    os.replace(result + ".partial", result)


if __name__ == "__main__":
    main(*sys.argv[1:])
