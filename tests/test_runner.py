"""The experiment runner: outputs, one-line errors, and resuming an interrupted sweep."""

import json
import os
import shutil
import signal
import subprocess
import sys
import time

import jax
import numpy as np
import pytest

import ot_filter as otf
from ot_filter.progress import progress_listener
from ot_filter.runner import EXPERIMENTS, RunError, resolve_options

# A small sweep: Lorenz-96 (n = 8), 2 methods x 4 blocks of one simulation = 8 cells; the blocks
# of a method share one compiled program, so a cell is its 10,000 steps (~0.3 s): long enough to
# be interrupted in the middle of the sweep.
STEPS = 10_000
SWEEP = ["run", "lorenz96", "--dim", "8", "--particles", "10", "--steps", str(STEPS), "--simulations", "4",
         "--block", "1", "--methods", "enkf,sir", "--no-progress"]


def _cli(*arguments):
    return subprocess.Popen([sys.executable, "-m", "ot_filter", *arguments], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def _finished_cells(out):
    cells = os.path.join(out, "cells")
    return sorted(f for f in os.listdir(cells) if f.endswith(".json")) if os.path.isdir(cells) else []


def _interrupt_after(out, cells, sig):
    """Starts the sweep, sends ``sig`` once ``cells`` cells are stored; returns (code, stderr)."""
    process = _cli(*SWEEP, "--out", out)
    deadline = time.monotonic() + 240
    while len(_finished_cells(out)) < cells and process.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    process.send_signal(sig)
    _, error = process.communicate(timeout=120)
    return process.returncode, error


@pytest.mark.long
def test_interrupted_sweep_resumes_and_reproduces_the_uninterrupted_metrics(tmp_path):
    whole = str(tmp_path / "whole")
    process = _cli(*SWEEP, "--out", whole)
    output, error = process.communicate(timeout=300)
    assert process.returncode == 0, error
    assert "ran 8 cells (0 already finished)" in output

    resumed = str(tmp_path / "resumed")
    code, error = _interrupt_after(resumed, 2, signal.SIGINT)  # stops after the running cell
    assert code == 130 and "rerun the same command to resume" in error and "Traceback" not in error
    after_sigint = len(_finished_cells(resumed))
    code, _ = _interrupt_after(resumed, after_sigint + 1, signal.SIGKILL)  # stops at once
    assert code == -signal.SIGKILL
    stored = _finished_cells(resumed)
    assert after_sigint < len(stored) < 8
    assert not os.path.exists(os.path.join(resumed, "metrics.json"))  # no summary before the end
    for name in os.listdir(os.path.join(resumed, "cells")):  # no half-written file under a final name
        assert not name.endswith(".tmp") or name.startswith(".")
    process = _cli(*SWEEP, "--out", resumed)
    output, error = process.communicate(timeout=300)
    assert process.returncode == 0, error
    assert f"ran {8 - len(stored)} cells ({len(stored)} already finished)" in output

    with open(os.path.join(whole, "metrics.json")) as a, open(os.path.join(resumed, "metrics.json")) as b:
        assert a.read() == b.read()
    config = json.load(open(os.path.join(whole, "config.json")))
    assert config["ot_filter_version"] == otf.__version__ and config["backend"] == jax.default_backend()
    assert config["options"]["particles"] == [10] and config["command"][:3] == ["ot-filter", "run", "lorenz96"]
    timings = json.load(open(os.path.join(whole, "timings.json")))
    assert timings["total_compile_s"] > 0 and timings["total_run_s"] > 0
    assert os.path.getsize(os.path.join(whole, "lorenz96_rmse.png")) > 10_000
    with np.load(os.path.join(whole, "arrays.npz")) as arrays:
        assert arrays["method-enkf_dim-8_particles-10/rmse_mean"].shape == (STEPS,)
    metrics = json.load(open(os.path.join(whole, "metrics.json")))
    for row in metrics["results"]:  # one row per method, the blocks' simulations joined in order
        values = row["per_simulation"]["rmse_a"]["values"]
        assert len(values) == 4 and np.all(np.isfinite(values))


@pytest.mark.parametrize(
    "arguments, message",
    [
        (["run", "nonexistent"], "unknown experiment 'nonexistent'; available: static, dynamic"),
        (["run", "lorenz63", "--dim", "3"], "--dim does not apply to lorenz63"),
        (["run", "dynamic", "--particles", "ten"], "expected integers separated by commas"),
        (["run", "dynamic", "--particles", "0"], "--particles must be a positive integer"),
        (["run", "dynamic", "--methods", "enkf,magic"], "unknown method(s) magic for dynamic"),
        (["run", "dynamic", "--dim", "2,4"], "--dim takes one value for dynamic"),
        (["run", "static", "--noise", "0.4,-1"], "--noise values must be > 0"),
        (["run", "lorenz63", "--map-gate", "-1"], "--map-gate must be a finite ratio > 0, or 0 for none"),
        (["run", "lorenz63", "--map-gate", "inf"], "--map-gate must be a finite ratio > 0, or 0 for none"),
        (["run", "static", "--map-gate", "1.25"], "--map-gate does not apply to static"),
        (["run", "dynamic", "--out", "/proc/forbidden"], "cannot write to output directory"),
        (["frobnicate"], "invalid choice: 'frobnicate'"),
    ],
)
def test_bad_names_options_and_directories_are_one_line_errors(arguments, message):
    process = _cli(*arguments)
    _, error = process.communicate(timeout=120)
    assert process.returncode == 2
    assert message in error and error.count("\n") == 1 and "Traceback" not in error


def test_a_directory_holding_another_run_is_refused(tmp_path):
    from ot_filter.runner.run import _config
    from ot_filter.runner.store import RunDirectory

    options = resolve_options("dynamic", {"particles": 50}, quick=True)
    RunDirectory.open(str(tmp_path), _config(options, True, []), ("experiment", "options"))
    other = resolve_options("dynamic", {"particles": 60}, quick=True)
    with pytest.raises(RunError, match="holds a different run"):
        RunDirectory.open(str(tmp_path), _config(other, True, []), ("experiment", "options"))


def test_the_runner_gives_the_offline_stage_its_map_gate(tmp_path, monkeypatch):
    # --map-gate reaches map_for's gate: by default the experiment's (None), none with --quick
    # (maps of 3,000 iterations would miss it and train every wave) or with 0.
    import ot_filter.experiments.amortised as amortised
    from ot_filter.runner.catalogue import _amortised

    class Reached(Exception):
        pass

    def offline_stage(directory, key, experiment, **options):
        raise Reached(options["gate"])

    monkeypatch.setattr(amortised, "map_for", offline_stage)
    for quick, overrides, gate in ((False, {}, None), (True, {}, False), (True, {"map_gate": 1.5}, 1.5),
                                   (False, {"map_gate": 0.0}, False)):
        options = dict(resolve_options("lorenz63", overrides, quick=quick), run_dir=str(tmp_path))
        with pytest.raises(Reached) as reached:
            _amortised(options, "lorenz63", "amortised", 40, observed=(0, 2))
        assert reached.value.args[0] is gate if gate is None or gate is False else reached.value.args[0] == gate


def test_list_names_every_experiment():
    process = _cli("list")
    output, _ = process.communicate(timeout=120)
    assert process.returncode == 0
    for name in EXPERIMENTS:
        assert name in output


@pytest.mark.long
def test_in_scan_progress_reports_and_is_absent_when_off():
    model = otf.models.lorenz63()
    _, observations = otf.simulate(jax.random.key(0), model, 100)
    reports = []
    with progress_listener(lambda done, total: reports.append((done, total))):
        otf.run_filter(jax.random.key(1), model, otf.enkf(), observations, 10, save_every=7,
                       progress=30).mean.block_until_ready()
        assert reports == [(30, 100), (60, 100), (90, 100), (100, 100)]
        reports.clear()
        otf.run_filter(jax.random.key(1), model, otf.enkf(), observations, 10, save_every=7).mean.block_until_ready()
        assert reports == []
    with pytest.raises(ValueError, match="progress must be an int >= 0"):
        otf.run_filter(jax.random.key(1), model, otf.enkf(), observations, 10, progress=-1)


@pytest.mark.long
def test_an_amortised_map_is_trained_once_stored_in_the_run_and_reused_by_a_later_run(tmp_path):
    from ot_filter.amortised import load_map
    from ot_filter.runner import run_experiment

    small = dict(particles=(40,), steps=3, simulations=2, block=1, map_iterations=60)
    first = run_experiment("dynamic", dict(small, methods=("amortised", "amortised_warm")), str(tmp_path / "first"),
                           progress=False, command=["test"], log=lambda line: None)
    stored = tmp_path / "first" / "maps" / "dynamic-n2"
    assert (stored / "map.json").exists() and (stored / "history.npz").exists()
    trained = load_map(stored, model="dynamic-n2", state_dim=2)
    assert trained.info["iterations"] == 60 and trained.info["rounds"] == 3
    # Both candidates (two trainings of the plain map on the dynamic example) were trained and
    # stored; the map kept is the one with the smaller MSE on the held-out truths, and the
    # offline cost counts both.
    selection = trained.info["selection"]
    candidates = {label: load_map(stored / "candidates" / label) for label in ("plain", "plain_second_training")}
    assert set(selection["scores"]) == set(candidates)
    assert selection["chosen"] == min(selection["scores"], key=lambda label: selection["scores"][label]["mse"])
    assert not any(candidate.config.enkf_layer for candidate in candidates.values())
    first_leaves, second_leaves = (jax.tree.leaves(candidate.params) for candidate in candidates.values())
    assert not all(np.allclose(a, b) for a, b in zip(first_leaves, second_leaves))  # two trainings, two keys
    for got, want in zip(jax.tree.leaves(trained.params), jax.tree.leaves(candidates[selection["chosen"]].params)):
        np.testing.assert_array_equal(got, want)
    assert selection["offline_seconds"] == pytest.approx(
        sum(one.info["seconds"] for one in candidates.values())
        + sum(score["seconds"] for score in selection["scores"].values()))
    for label in candidates:  # each score keeps its per-truth errors: as many truths as the offline bank
        assert len(selection["scores"][label]["per_simulation"]) == trained.info["simulations"]
    # An interrupted offline stage resumes from the candidates it stored, if trained the same way.
    from ot_filter.experiments.amortised import map_for
    from ot_filter.runner.catalogue import cell_key

    resumed = tmp_path / "resumed"
    for label in candidates:
        shutil.copytree(stored / "candidates" / label, resumed / "candidates" / label)
    same = dict(num_particles=40, num_steps=3, num_iterations=60)
    again, histories = map_for(str(resumed), cell_key(0, 999_983), "dynamic", **same)
    assert histories is None and again.info["selection"]["chosen"] == selection["chosen"]
    for got, want in zip(jax.tree.leaves(again.params), jax.tree.leaves(candidates[selection["chosen"]].params)):
        np.testing.assert_array_equal(got, want)
    # A candidate trained with other options is refused, not ranked against fresh ones.
    stale = tmp_path / "stale"
    shutil.copytree(stored / "candidates" / "plain", stale / "candidates" / "plain")
    with pytest.raises(ValueError, match="trained with other options"):
        map_for(str(stale), cell_key(0, 999_983), "dynamic", candidates={"plain": {}},
                **dict(same, num_iterations=120))
    rows = {row["method"]: row for row in first.metrics["results"]}
    assert set(rows) == {"amortised", "amortised_warm"}
    for row in rows.values():
        assert np.all(np.isfinite(row["per_simulation"]["w1"]["values"]))
    written = os.path.getmtime(stored / "map.json")
    # A later run (another directory) that points at the stored maps trains nothing.
    run_experiment("dynamic", dict(small, methods=("amortised",), maps=str(tmp_path / "first" / "maps")),
                   str(tmp_path / "second"), progress=False, command=["test"], log=lambda line: None)
    assert os.path.getmtime(stored / "map.json") == written
    assert not (tmp_path / "second" / "maps").exists()


@pytest.mark.long
def test_the_distilled_method_fits_the_kept_map_into_narrower_networks_stored_beside_it(tmp_path):
    from ot_filter.amortised import load_map
    from ot_filter.experiments.amortised import DISTILLED_WIDTH, DYNAMIC_CANDIDATES, same_setting_candidates
    from ot_filter.runner import run_experiment

    small = dict(particles=(40,), steps=3, simulations=2, block=1, map_iterations=60, methods=("amortised_distilled",))
    first = run_experiment("dynamic", small, str(tmp_path / "first"), progress=False, command=["test"],
                           log=lambda line: None)
    teacher = load_map(tmp_path / "first" / "maps" / "dynamic-n2", model="dynamic-n2", state_dim=2)
    stored = tmp_path / "first" / "maps" / "dynamic-n2" / "distilled"
    student = load_map(stored, model="dynamic-n2", state_dim=2)
    assert student.config == teacher.config._replace(width=DISTILLED_WIDTH)
    assert student.info["distilled_from"]["width"] == teacher.config.width
    # The dynamic example's offline stage trains the plain map twice: the student fits both
    # unless the held-out selection found one worse.
    teachers = same_setting_candidates(str(tmp_path / "first" / "maps" / "dynamic-n2"), teacher)
    assert len(student.info["distilled_from"].get("teachers", [None])) == len(teachers)
    assert len(teachers) in (1, len(DYNAMIC_CANDIDATES))
    assert student.info["distillation"]["iterations"] == 60
    (row,) = first.metrics["results"]
    assert row["method"] == "amortised_distilled" and np.all(np.isfinite(row["per_simulation"]["w1"]["values"]))
    written = os.path.getmtime(stored / "map.json")
    # A later run pointed at the stored maps distils nothing again.
    run_experiment("dynamic", dict(small, maps=str(tmp_path / "first" / "maps")), str(tmp_path / "second"),
                   progress=False, command=["test"], log=lambda line: None)
    assert os.path.getmtime(stored / "map.json") == written


@pytest.mark.long
def test_a_local_offline_map_is_trained_once_stored_in_the_run_and_reused_by_a_later_run(tmp_path, monkeypatch):
    """Methods local_amortised and local_amortised_warm: the first cell trains the dynamic
    example's local map into the run's maps/ (with its validation curve), later cells and runs
    reload it, and a map of another n is not taken for this one."""
    from ot_filter.amortised import load_local_map
    from ot_filter.experiments import local_amortised
    from ot_filter.runner import run_experiment

    monkeypatch.setattr(local_amortised, "MIN_SIMULATIONS", 2)  # a small bank: the test is of the plumbing
    monkeypatch.setattr(local_amortised, "MAX_SIMULATIONS", 3)
    small = dict(particles=(40,), steps=3, simulations=2, block=1, map_iterations=40)
    first = run_experiment("dynamic", dict(small, methods=local_amortised.METHODS), str(tmp_path / "first"),
                           progress=False, command=["test"], log=lambda line: None)
    stored = tmp_path / "first" / "maps" / "dynamic-n2-local"
    trained = load_local_map(stored, model="dynamic-n2-local", state_dim=2)
    assert trained.info["iterations"] == 40 and trained.info["simulations"] == 3
    with np.load(stored / "history.npz") as history:
        assert history["validation_loss"].shape == (20,) and np.all(np.isfinite(history["validation_loss"]))
    rows = {row["method"]: row for row in first.metrics["results"]}
    assert set(rows) == set(local_amortised.METHODS)
    assert (tmp_path / "first" / "offline_training.png").exists()  # the validation curve
    for row in rows.values():
        assert np.all(np.isfinite(row["per_simulation"]["w1"]["values"]))
    written = os.path.getmtime(stored / "map.json")
    run_experiment("dynamic", dict(small, methods=("local_amortised",), maps=str(tmp_path / "first" / "maps")),
                   str(tmp_path / "second"), progress=False, command=["test"], log=lambda line: None)
    assert os.path.getmtime(stored / "map.json") == written
    assert not (tmp_path / "second" / "maps").exists()
    shutil.copytree(stored, tmp_path / "wrong" / "dynamic-n2-local")  # n = 2's map where n = 3's is looked for
    os.rename(tmp_path / "wrong" / "dynamic-n2-local", tmp_path / "wrong" / "dynamic-n3-local")
    with pytest.raises(Exception, match="trained for model 'dynamic-n2-local'"):
        run_experiment("dynamic", dict(small, dim=(3,), methods=("local_amortised",), maps=str(tmp_path / "wrong")),
                       str(tmp_path / "third"), progress=False, command=["test"], log=lambda line: None)


def test_the_lorenz96_catalogue_keeps_the_batches_its_figures_were_measured_with():
    """local_ot's default mini-batch is 512 local pairs (0.2.19); the Lorenz-96 catalogue's
    localised filter keeps 128, with which every Lorenz-96 figure was measured, unless told."""
    from ot_filter.runner.catalogue import lorenz96_local_ot
    from ot_filter.updates.local_ot import local_update_parts

    model = otf.models.lorenz96(dim=12)
    default = otf.local_ot(otf.local_windows(model.geometry, 0.0))
    assert local_update_parts(default)[1].batch_size == 512
    assert local_update_parts(lorenz96_local_ot(model, 64))[1].batch_size == 128
    assert local_update_parts(lorenz96_local_ot(model, 64, batch_size=256))[1].batch_size == 256
