"""ot_filter: nonlinear filtering and Bayesian posterior sampling in JAX.

Models are pytrees of per-particle functions (``StateSpaceModel``); Bayes updates are builders
returning ``BayesUpdate(init, apply)`` (``sir``, ``enkf``, ``letkf``, ``local_etpf``, ``ot``, ``local_ot``, ``flow_matching``, ``local_flow``, and ``amortised_ot`` with a map trained offline by
``amortised``; ``split_likelihood`` chains them on powers of the likelihood; ``averaged_maps``
averages several trainings of a map);
``localisation`` describes where the state and observations lie (``ring``, ``points``) and builds
the taper and the local windows; ``run_filter`` composes them into a
whole-trajectory filter in one ``lax.scan``; ``kalman_filter`` is the exact reference. ``continuous`` holds the continuous-time part
(``SDEModel``, Kalman-Bucy, the feedback particle filter and its gains).
"""

from ot_filter import continuous, metrics, models, reference
from ot_filter.localisation import Geometry, LocalWindows, Localisation, local_windows, localisation, points, ring
from ot_filter.continuous import SDEModel
from ot_filter.filtering import FilterResult, run_filter
from ot_filter.kalman import KalmanResult, kalman_filter
from ot_filter.model import StateSpaceModel, simulate, simulate_observations
from ot_filter.sharding import particle_sharding
from ot_filter.updates import (
    BayesUpdate,
    averaged_maps,
    EnKFInfo,
    LETKFInfo,
    OTInfo,
    OTState,
    OTUpdate,
    SIRInfo,
    SIRState,
    enkf,
    flow_matching,
    FlowInfo,
    FlowState,
    FlowUpdate,
    letkf,
    local_etpf,
    local_flow,
    local_ot,
    ot,
    resample_indices,
    sir,
    split_likelihood,
    tempered_model,
)
from ot_filter.updates.amortised import amortised_ot
from ot_filter import amortised

__version__ = "0.2.22"  # 0.2: ot() sizes its networks from n; f rate 3e-4 (run directories of 0.1 are not resumed);
#                       0.2.1: amortised (b) on Lorenz-63 warm-starts with (32, 8) iterations (a run directory
#                       of another version is not resumed: its cells would mix the two);
#                       0.2.2: amortised maps above n = 4 train on larger batches, (b) there trains more a step;
#                       0.2.3: the dynamic example's amortised maps train on a bank that grows with n, and
#                       above n = 4 a fourth round
#                       0.2.4: the experiments compile at XLA's LLVM level 1 on a CPU (results round differently);
#                       the offline candidates train at once, a worker process each
#                       0.2.5: the dynamic example's amortised maps above n = 4 average each round's iterates
#                       0.2.6: ot()'s default width grows with n above n = 18 (128, then 256 from n = 37)
#                       0.2.7: ot()'s default prior_smoothing is 1.5 (was 1)
#                       0.2.8: local_ot's layer gain has the ridge of its observation slots alone; a local
#                       map used as is is tabulated at 128 knots (map_knots); its checks read CHECK_ROWS particles
#                       0.2.9: the OT updates and the offline bank simulate observations with additive Gaussian
#                       noise as h(X) + noise drawn a component at a time (simulate_observations): other draws
#                       0.2.10: the runner's amortised_distilled fits the average of the offline stage's
#                       trainings of the kept map's setting (the dynamic example's two), width 16 up to n = 3 only
#                       0.2.11: Lorenz-63's offline stage trains each candidate setting twice and averages the
#                       last round's iterates (the last iterate, (b)'s start, unchanged)
#                       0.2.12: the offline stage selects its map on truths like the experiment's
#                       (Lorenz-63's start away from the filter's prior; its score skips t <= 1.5), and on
#                       Lorenz-63 (b)'s start, a plain map, by (b)'s own score (MAP/warm)
#                       0.2.13: Lorenz-63's offline stage holds its kept map's (a) to 1.25 times the online OT
#                       filter's MSE on the held-out truths, training further candidates while it is over (gate)
#                       0.2.14: amortised (b) on Lorenz-63 warm-starts with (32, 16) iterations a step (was (32, 8))
#                       0.2.15: lorenz96 takes observation_operator="abs" (y = |x| + noise)
#                       0.2.16: local_etpf, split_likelihood and tempered_model; the runner's lorenz96 offers
#                       letkf_etpf (the LETKF on l^0.75, the localised ETPF on l^0.25)
#                       0.2.17: the runner's lorenz96 and the experiments offer local_ot_etpf (the localised
#                       OT update on l^0.75, the localised ETPF on l^0.25)
#                       0.2.18: averaged_maps (K trainings of a map, their outputs averaged); the experiments
#                       offer <method>_avg<K> for ot and local_ot
#                       0.2.19: local_ot's mini-batches are 512 local pairs (were 128); the Lorenz-96
#                       catalogue keeps 128 (what its figures were measured with)
#                       0.2.20: local_ot(fresh_observations=True) draws each mini-batch's local
#                       observations afresh (off by default)
#                       0.2.21: flow_matching (a conditional transport learned by regression)
#                       0.2.22: local_flow (local_ot's windows and layers with flow_matching's regression)

__all__ = [
    "BayesUpdate",
    "EnKFInfo",
    "FilterResult",
    "Geometry",
    "KalmanResult",
    "LETKFInfo",
    "LocalWindows",
    "Localisation",
    "OTInfo",
    "OTState",
    "OTUpdate",
    "SIRInfo",
    "SIRState",
    "SDEModel",
    "StateSpaceModel",
    "amortised",
    "amortised_ot",
    "averaged_maps",
    "continuous",
    "enkf",
    "flow_matching",
    "FlowInfo",
    "FlowState",
    "FlowUpdate",
    "kalman_filter",
    "letkf",
    "local_etpf",
    "local_flow",
    "local_ot",
    "local_windows",
    "localisation",
    "metrics",
    "models",
    "ot",
    "particle_sharding",
    "points",
    "reference",
    "resample_indices",
    "ring",
    "run_filter",
    "simulate",
    "simulate_observations",
    "sir",
    "split_likelihood",
    "tempered_model",
]
