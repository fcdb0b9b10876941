"""Amortised OT filtering: a conditional map trained offline on the forecast ensembles of long
simulated trajectories (``training``, ``bank``), chosen among candidates by how well its filter
tracks simulated truths (``selection``), saved and loaded with its record (``storage``), and
filtered with by ``ot_filter.amortised_ot`` (no training online, or a few warm-started
iterations per step; ``distillation``: a found map fitted into narrower networks for a cheaper
step). ``local``: the localised update's shared map trained offline the same way
(filtered with by ``ot_filter.local_ot(..., initial_map=...)``)."""

from ot_filter.amortised.bank import ForecastBank, bank_batch, forecast_bank, split_bank
from ot_filter.amortised.distillation import DistillationHistory, distil_map
from ot_filter.amortised.local import (
    LocalBank,
    LocalMap,
    LocalMapConfig,
    amortised_local_ot,
    local_bank,
    local_bank_batch,
    train_local_amortised,
    train_local_map,
)
from ot_filter.amortised.selection import MapScore, score_filter, score_map, select_map
from ot_filter.amortised.storage import MapMismatchError, load_local_map, load_map, save_local_map, save_map
from ot_filter.amortised.training import (
    AmortisedMap,
    MapConfig,
    TrainingHistory,
    collect_forecasts,
    map_recipe,
    stack_banks,
    train_amortised,
    train_amortised_seeds,
    train_map,
    train_maps,
)

__all__ = [
    "AmortisedMap",
    "DistillationHistory",
    "ForecastBank",
    "LocalBank",
    "LocalMap",
    "LocalMapConfig",
    "MapConfig",
    "MapMismatchError",
    "MapScore",
    "TrainingHistory",
    "amortised_local_ot",
    "bank_batch",
    "collect_forecasts",
    "distil_map",
    "forecast_bank",
    "local_bank",
    "local_bank_batch",
    "load_local_map",
    "load_map",
    "map_recipe",
    "save_local_map",
    "save_map",
    "score_filter",
    "score_map",
    "select_map",
    "split_bank",
    "stack_banks",
    "train_amortised",
    "train_amortised_seeds",
    "train_local_amortised",
    "train_local_map",
    "train_map",
    "train_maps",
]
