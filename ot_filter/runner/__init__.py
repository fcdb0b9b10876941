"""The experiment runner behind ``ot-filter run``: a catalogue of experiments split into
resumable cells, an output directory written atomically, progress reports, and figures."""

from ot_filter.runner.catalogue import EXPERIMENTS, CellOutput, Experiment
from ot_filter.runner.run import RunInterrupted, RunOutput, resolve_options, run_experiment
from ot_filter.runner.store import RunDirectory, RunError

__all__ = [
    "EXPERIMENTS",
    "CellOutput",
    "Experiment",
    "RunDirectory",
    "RunError",
    "RunInterrupted",
    "RunOutput",
    "resolve_options",
    "run_experiment",
]
