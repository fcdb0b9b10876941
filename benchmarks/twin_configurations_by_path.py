"""``ot_filter/experiments/twin_configurations.py`` loaded by file path, for the baseline scripts
that run in DAPPER's or cuthbert's own interpreter (which need not have ot_filter installed; the
module imports neither ot_filter nor JAX at import time)."""

import importlib.util
import sys
from pathlib import Path


def load_twin_configurations():
    path = Path(__file__).resolve().parents[1] / "ot_filter" / "experiments" / "twin_configurations.py"
    spec = importlib.util.spec_from_file_location("_twin_configurations", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module
