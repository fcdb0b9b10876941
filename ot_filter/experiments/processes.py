"""Functions run at the same time in worker processes of their own, one CPU core each.

``start(jobs)`` launches ``{label: ("module:function", kwargs)}`` as
``python -m ot_filter.experiments.processes IN OUT`` processes and returns at once; the caller
works meanwhile and collects the return values with ``Started.results()``. Arguments and return
values travel pickled, so they are NumPy arrays and plain data (a PRNG key as its
``jax.random.key_data``). Each worker's JAX has one single-threaded CPU device (the CLI's setting
per core, ``_common.host_devices_for_cpu_cores``) and the caller's precision (x64 or not).

Processes, not threads: two programs run at once from two threads of one process hung in XLA's
CPU runtime (two offline maps trained at n = 10: three tries of three); processes share nothing.
Meant for a CPU backend: a worker would start a JAX of its own on an accelerator.
"""

from __future__ import annotations

import importlib
import os
import pickle
import subprocess
import sys
import tempfile
import time
from typing import NamedTuple


def worker_environment(environ=os.environ) -> dict:
    """``environ`` with XLA_FLAGS for one single-threaded host device (the parent's other flags,
    such as its compiler options, kept)."""
    flags = [flag for flag in environ.get("XLA_FLAGS", "").split()
             if flag.startswith("--")
             and not flag.startswith(("--xla_force_host_platform_device_count", "--xla_cpu_multi_thread_eigen"))]
    return dict(environ, XLA_FLAGS=" ".join(flags + ["--xla_cpu_multi_thread_eigen=false"]))


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
                        with open(log.name) as handle:
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
        """Kills the workers still running and removes the scratch directory."""
        for process, log, _ in self.running.values():
            if process.poll() is None:
                process.kill()
                process.wait()
            log.close()
        self.scratch.cleanup()


def start(jobs: dict) -> Started:
    """Launches every ``{label: ("module:function", kwargs)}`` job in a worker process."""
    scratch = tempfile.TemporaryDirectory(prefix="ot_filter_workers_")
    environment = worker_environment()
    jax = sys.modules.get("jax")
    if jax is not None and jax.config.jax_enable_x64:  # the workers compute in the caller's precision
        environment["JAX_ENABLE_X64"] = "1"
    running = {}
    try:
        for label, (target, kwargs) in jobs.items():
            if ":" not in target:
                raise ValueError(f"job {label!r}: target {target!r} is not 'module:function'")
            arguments = os.path.join(scratch.name, f"{label}.in.pickle")
            result = os.path.join(scratch.name, f"{label}.out.pickle")
            with open(arguments, "wb") as handle:
                pickle.dump((target, kwargs), handle)
            log = open(os.path.join(scratch.name, f"{label}.log"), "w")
            process = subprocess.Popen([sys.executable, "-m", __name__, arguments, result],
                                       env=environment, stdout=log, stderr=subprocess.STDOUT)
            running[label] = (process, log, result)
    except BaseException:
        Started(running, scratch).stop()
        raise
    return Started(running, scratch)


def run(jobs: dict) -> dict:
    """``start(jobs).results()``: every job at once, waited for."""
    return start(jobs).results()


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
