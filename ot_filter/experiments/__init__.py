"""The chapter's experiments as functions returning numbers and writing figures, callable from
benchmark scripts, the command line and notebooks alike."""

from ot_filter.experiments.static_example import plot_static_example, run_static_example

__all__ = ["plot_static_example", "run_static_example"]
