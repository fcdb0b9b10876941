"""Progress reports from inside jit-compiled scans, switched on per call and cheap when on.

A filter run with ``progress=k`` (``run_filter``, ``run_fpf``) calls ``jax.debug.callback`` after
every k-th step (and the last) with ``(steps done, total)``; the host forwards it to the
listeners registered with ``progress_listener``. With ``progress=0`` (the default) the compiled
program contains no callback at all. Under ``vmap`` every simulation reports the same step; the
listeners get the largest. ``every_fraction`` picks a k for about 20 reports a run.

Cost (``benchmarks/results/progress_overhead.md``, medians of 15 alternating runs): about
0.3 ms per report on the host plus a ``lax.cond`` per step. Under 1 % on the long filters the
reports are for (OT filter: within noise; kernel-gain FPF: +0.4 %), +5 % on a 0.9 s constant-gain
FPF, +10 % on a 0.37 s Lorenz-96 EnKF (an earlier 9-run measurement gave +4 % / +3 %: these
sub-second runs are noisy on a shared 2-core machine), +66 % on a 17 ms run (Lorenz-63 EnKF,
N = 10). Scanning in chunks with the callback between them was measured too: better on the tiny
run (+40 %), worse on the sub-second ones (+13 %); rejected.
"""

from __future__ import annotations

import contextlib
from typing import Callable, Iterator

import jax
import numpy as np

__all__ = ["every_fraction", "maybe_report", "progress_listener", "report"]

_LISTENERS: list[Callable[[int, int], None]] = []


def _dispatch(done, total) -> None:
    done, total = int(np.max(done)), int(np.max(total))
    for listener in list(_LISTENERS):
        listener(done, total)


def report(done: int, total: int) -> None:
    """From host code (a loop of compiled chunks, e.g. offline training): tell the listeners."""
    _dispatch(done, total)


@contextlib.contextmanager
def progress_listener(listener: Callable[[int, int], None]) -> Iterator[None]:
    """Within the block, ``listener(done, total)`` receives the reports of running filters."""
    _LISTENERS.append(listener)
    try:
        yield
    finally:
        _LISTENERS.remove(listener)


def every_fraction(num_steps: int, reports: int = 20) -> int:
    """The report interval for about ``reports`` reports over ``num_steps`` steps."""
    return max(1, int(num_steps) // max(1, int(reports)))


def maybe_report(index, num_steps: int, every: int) -> None:
    """Inside a scan body: report ``index + 1`` of ``num_steps`` if it is a multiple of ``every``
    or the last step (``every`` static, > 0)."""
    done = index + 1
    due = (done % every == 0) | (done == num_steps)
    jax.lax.cond(
        due,
        lambda: jax.debug.callback(_dispatch, done, num_steps),
        lambda: None,
    )
