"""One offline candidate map trained in a process of its own (``amortised.map_for``'s workers).

``python -m ot_filter.experiments.candidate_worker ARGS.pickle``: ``ARGS`` holds the arguments of
``amortised._candidate`` with the key as its raw data; the worker trains the candidate and stores
it in its directory, where the parent reloads it. A process per candidate, not a thread: two
maps trained at once from two threads of one process hung in XLA's CPU runtime (n = 10, three
tries of three), separate processes share nothing.
"""

from __future__ import annotations

import pickle
import sys


def main(path: str) -> None:
    with open(path, "rb") as handle:
        arguments = pickle.load(handle)
    import jax

    from ot_filter.experiments.amortised import _candidate

    key = jax.random.wrap_key_data(arguments.pop("key_data"))
    _candidate(arguments.pop("where"), key, **arguments)


if __name__ == "__main__":
    main(sys.argv[1])
