"""The demo command: runs, writes its figure and numbers, reaches the published accuracy."""

import json

import pytest

from ot_filter.cli import main


@pytest.mark.long
def test_demo_writes_outputs(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out)]) == 0
    assert (out / "demo.png").stat().st_size > 10_000
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["EnKF (square root, N=10)"]["rmse_a"] < 0.8
    assert metrics["SIR (regularised, N=800)"]["rmse_a"] < 0.4
    # The bimodal part: the OT filters hold both modes where the EnKF cannot and SIR collapses
    # (n = 10); W1 to the exact filter, with the N-sample floor about 0.04.
    bimodal = metrics["bimodal"]
    assert (out / "demo_bimodal.png").stat().st_size > 10_000
    assert bimodal["OT (localised)"]["w1"] < 0.5 * min(bimodal["EnKF"]["w1"], bimodal["SIR"]["w1"])
    assert bimodal["OT (global)"]["w1"] < bimodal["EnKF"]["w1"]
    assert "wrote" in capsys.readouterr().out


def test_demo_unwritable_output_is_a_one_line_error(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    assert main(["demo", "--out", str(blocker / "sub")]) == 2
    error = capsys.readouterr().err
    assert error.startswith("ot-filter: error:") and error.count("\n") == 1


def test_compile_cache_directory_follows_the_environment():
    from ot_filter.cli import compile_cache_directory

    assert compile_cache_directory({"OT_FILTER_COMPILE_CACHE": "/tmp/x"}) == "/tmp/x"
    assert compile_cache_directory({"OT_FILTER_COMPILE_CACHE": "off"}) is None
    assert compile_cache_directory({"OT_FILTER_COMPILE_CACHE": ""}) is None
    assert compile_cache_directory({"XDG_CACHE_HOME": "/c"}) == "/c/ot_filter/jax"
    assert compile_cache_directory({}).endswith(".cache/ot_filter/jax")


def test_compile_cache_stores_programs_and_respects_a_callers_choice(tmp_path):
    """In a fresh process (JAX's cache is configured once): the CLI's cache receives a compiled
    program, and a directory the caller gave JAX wins over the CLI's."""
    import subprocess
    import sys

    script = (
        "import jax, sys\n"
        "from ot_filter.cli import use_compile_cache\n"
        "jax.config.update('jax_persistent_cache_min_compile_time_secs', 0)\n"
        "use_compile_cache(sys.argv[1])\n"
        "print(jax.config.jax_compilation_cache_dir)\n"
        "jax.jit(lambda x: jax.numpy.sin(x) * 3)(jax.numpy.ones(7)).block_until_ready()\n"
    )
    ours, callers = tmp_path / "ours", tmp_path / "callers"
    run = subprocess.run([sys.executable, "-c", script, str(ours)], capture_output=True, text=True, check=True)
    assert run.stdout.strip() == str(ours)
    assert any(ours.rglob("*")), "nothing was written to the compilation cache"
    environment = dict(__import__("os").environ, JAX_COMPILATION_CACHE_DIR=str(callers))
    run = subprocess.run([sys.executable, "-c", script, str(tmp_path / "unused")], capture_output=True, text=True,
                         check=True, env=environment)
    assert run.stdout.strip() == str(callers)
    assert not (tmp_path / "unused").exists()
