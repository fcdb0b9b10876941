"""Worker processes (``experiments.processes``) and the dynamic example's methods run in them."""

import os
import subprocess
import time

import jax
import numpy as np
import pytest

from ot_filter.experiments import processes


def test_jobs_run_in_worker_processes_and_return_their_values():
    values = processes.run({"a": ("os:getpid", {}), "b": ("builtins:dict", {"x": np.arange(3), "y": "text"})})
    assert values["a"] != os.getpid()  # another process
    np.testing.assert_array_equal(values["b"]["x"], np.arange(3))
    assert values["b"]["y"] == "text"


@pytest.mark.skipif(not hasattr(os, "sched_getaffinity"), reason="the OS cannot pin processes")
def test_each_worker_is_pinned_to_one_of_the_caller_s_cores_from_the_last():
    assert [processes.core_for(index, [0, 1, 2]) for index in range(5)] == [2, 1, 0, 2, 1]
    cores = sorted(os.sched_getaffinity(0))
    values = processes.run({f"w{index}": ("ot_filter.experiments.processes:_cores", {}) for index in range(3)})
    assert [values[f"w{index}"] for index in range(3)] == [[cores[-1 - index % len(cores)]] for index in range(3)]
    assert sorted(os.sched_getaffinity(0)) == cores  # the caller is not pinned


def test_a_failing_worker_raises_with_its_output_and_stops_the_others():
    started = time.perf_counter()
    with pytest.raises(RuntimeError, match="(?s)bad: .*no attribute 'no_such_function'"):
        processes.run({"slow": ("subprocess:call", {"args": ["sleep", "61.25"]}),
                       "bad": ("ot_filter.experiments.processes:no_such_function", {})})
    assert time.perf_counter() - started < 30  # the sleeping worker was not waited for
    # ... and what it started went with it (the worker's whole session was killed).
    assert subprocess.run(["pgrep", "-f", "sleep 61.25"], capture_output=True).stdout == b""
    with pytest.raises(ValueError, match="job 'odd'.*module:function"):
        processes.start({"odd": ("os.getpid", {})})
    with pytest.raises(ValueError, match="label '../x' must be an identifier"):
        processes.start({"../x": ("os:getpid", {})})


def test_workers_get_one_single_threaded_device_and_keep_the_other_flags():
    environment = processes.worker_environment(
        {"XLA_FLAGS": "--xla_force_host_platform_device_count=2 --xla_cpu_multi_thread_eigen=true "
                      "--xla_dump_to=/tmp/x stray_token", "PATH": "/bin"})
    assert environment["XLA_FLAGS"].split() == ["--xla_dump_to=/tmp/x", "--xla_cpu_multi_thread_eigen=false"]
    assert environment["PATH"] == "/bin" and environment["JAX_PLATFORMS"] == "cpu"


def test_workers_take_the_caller_s_precision_compile_cache_and_package(tmp_path):
    import ot_filter

    root = os.path.dirname(os.path.dirname(ot_filter.__file__))
    for x64 in (True, False):
        with jax.enable_x64(x64):
            values = processes.run({"flags": ("ot_filter.experiments.processes:_jax_settings", {})})
        assert values["flags"]["x64"] == x64
    previous = jax.config.jax_compilation_cache_dir
    try:
        jax.config.update("jax_compilation_cache_dir", str(tmp_path))
        values = processes.run({"flags": ("ot_filter.experiments.processes:_jax_settings", {})})
    finally:
        jax.config.update("jax_compilation_cache_dir", previous)
    assert values["flags"]["cache"] == str(tmp_path)
    assert values["flags"]["backend"] == "cpu"
    assert os.path.samefile(os.path.dirname(values["flags"]["package"]), root)


@pytest.mark.long  # a worker process imports JAX and compiles the OT filter; the same filter here
def test_a_method_filtered_in_a_worker_process_is_the_method_filtered_here(x64):
    # Same keys, same float64 arithmetic (the worker takes the caller's precision): the OT
    # filter's particles agree to rounding, the EnKF run here alone is untouched.
    from ot_filter.experiments.dynamic_example import run_dynamic_example

    settings = dict(dim=2, num_particles=48, num_steps=3, num_simulations=2, methods=("enkf", "ot"),
                    ot_options={"num_iterations": (16, 4)}, keep=2, average_from=0.1)
    there = run_dynamic_example(jax.random.key(3), in_processes=("ot",), **settings)
    here = run_dynamic_example(jax.random.key(3), **settings)
    for name in ("enkf_particles", "ot_particles", "ot_log_weights"):
        assert there["arrays"][name].dtype == np.float64
        np.testing.assert_allclose(there["arrays"][name], here["arrays"][name], rtol=1e-8, atol=1e-8)
    for name in ("enkf", "ot"):
        assert there["metrics"][name]["exact"]["w1"]["mean"] == pytest.approx(here["metrics"][name]["exact"]["w1"]["mean"],
                                                                              rel=1e-6)
    with pytest.raises(ValueError, match=r"in_processes \['letkf'\] are not among the methods"):
        run_dynamic_example(jax.random.key(3), in_processes=("letkf",), **settings)
