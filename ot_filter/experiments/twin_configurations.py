"""DAPPER's twin-experiment configurations, in one place.

The Lorenz-63 settings come from DAPPER's ``dapper/mods/Lorenz63/sakov2012.py`` (Sakov et al.
2012) and the Lorenz-96 ones from ``dapper/mods/Lorenz96/sakov2008.py`` (Sakov & Oke 2008):
the model (``ot_filter.models.lorenz63()`` / ``lorenz96()`` default to them), the number of
analyses and the burn-in DAPPER averages after (``TWIN_EXPERIMENTS``), and each method's tuning
with the rmse.a DAPPER publishes for it (``TWIN_CONFIGURATIONS``). The demo, the ``lorenz96``
runner experiment, the benchmarks and the tests read them from here.

This file imports neither JAX nor ot_filter at import time (only when an update or a model is
built), so the DAPPER and cuthbert baselines, which run in interpreters of their own, load it by
file path for the numbers.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

__all__ = [
    "TWIN_CONFIGURATIONS",
    "TWIN_EXPERIMENTS",
    "TwinConfiguration",
    "TwinExperiment",
    "twin_model",
]


def twin_model(model_name: str, **overrides: Any):
    """``ot_filter.models.lorenz63()`` or ``lorenz96()`` (DAPPER's settings by default);
    ``overrides`` go to the model builder (e.g. ``dim=80``)."""
    from ot_filter import models

    if model_name not in TWIN_EXPERIMENTS:
        raise ValueError(f"unknown twin model {model_name!r}; choose from {sorted(TWIN_EXPERIMENTS)}")
    return getattr(models, model_name)(**overrides)


class TwinExperiment(NamedTuple):
    """A twin experiment's model and DAPPER's cycle conventions."""

    model_name: str  # 'lorenz63' | 'lorenz96'
    dapper_model: str  # DAPPER's model file, under dapper/mods
    num_analyses: int  # DAPPER's Ko + 1: the number of observations / analyses (cycles)
    dt_obs: float  # time between observations
    burn_in_time: float  # DAPPER's BurnIn: analyses at t = dt_obs (k + 1) <= BurnIn are not averaged
    analyses_averaged: int  # how many analyses DAPPER averages (HMM.tseq.masko.sum()), a check

    @property
    def burn_in(self) -> int:
        """Index of the first averaged analysis (0-based), i.e. the analyses skipped."""
        return int(round(self.burn_in_time / self.dt_obs))

    def make_model(self, **overrides: Any):
        return twin_model(self.model_name, **overrides)


TWIN_EXPERIMENTS = {
    "lorenz63": TwinExperiment("lorenz63", "Lorenz63/sakov2012.py", 1001, 0.25, 16.0, 937),
    "lorenz96": TwinExperiment("lorenz96", "Lorenz96/sakov2008.py", 1001, 0.05, 20.0, 601),
}


class TwinConfiguration(NamedTuple):
    """One filter configuration of a twin experiment, as DAPPER tunes it."""

    name: str  # e.g. "L63/EnKF-Sqrt-N10" (the benchmarks' key)
    model_name: str  # 'lorenz63' | 'lorenz96' (a key of TWIN_EXPERIMENTS)
    label: str  # short name of the method for tables, e.g. "EnKF Sqrt infl 1.02 rot"
    description: str
    num_particles: int
    update_factory: Callable[..., Any]  # settings as keywords -> ot_filter BayesUpdate
    settings: dict  # the numeric settings, e.g. {"inflation": 1.02}
    dapper_method: str  # the DAPPER call (dapper.da_methods)
    expected_rmse: float | None  # rmse.a published in DAPPER's model file (None: not published)

    def build_update(self, **overrides: float):
        """The ot_filter update with ``settings``, some overridden (``inflation=1.05``)."""
        unknown = set(overrides) - set(self.settings)
        if unknown:
            raise TypeError(f"{self.name}: unknown settings {sorted(unknown)}; "
                            f"it has {sorted(self.settings)}")
        return self.update_factory(**{**self.settings, **overrides})

    @property
    def experiment(self) -> TwinExperiment:
        return TWIN_EXPERIMENTS[self.model_name]


def _enkf(perturbed: bool, rotate: bool) -> Callable[..., Any]:
    def build(inflation: float):
        from ot_filter import enkf

        return enkf(inflation=inflation, perturbed=perturbed, rotate=rotate)

    return build


def _sir(ess_threshold: float, jitter: float):
    from ot_filter import sir

    return sir(resampling="systematic", ess_threshold=ess_threshold, jitter=jitter)


TWIN_CONFIGURATIONS = {
    c.name: c
    for c in (
        TwinConfiguration(
            "L63/EnKF-Sqrt-N10", "lorenz63", "EnKF Sqrt infl 1.02 rot",
            "Lorenz-63: square-root EnKF (random mean-preserving rotation), 10 members, "
            "inflation 1.02", 10, _enkf(perturbed=False, rotate=True), {"inflation": 1.02},
            "EnKF('Sqrt', N=10, infl=1.02, rot=True)", 0.60,
        ),
        TwinConfiguration(
            "L63/EnKF-PertObs-N10", "lorenz63", "EnKF PertObs infl 1.02",
            "Lorenz-63: perturbed-observation EnKF, 10 members, inflation 1.02 (no published "
            "rmse.a; cuthbert has this EnKF)", 10, _enkf(perturbed=True, rotate=False),
            {"inflation": 1.02}, "EnKF('PertObs', N=10, infl=1.02)", None,
        ),
        TwinConfiguration(
            "L63/PartFilt-N800", "lorenz63", "PartFilt reg 0.9 NER 0.2",
            "Lorenz-63: regularised SIR (systematic resampling when ESS < 0.2 N, jitter 0.9 "
            "as DAPPER's reg), 800 particles", 800, _sir,
            {"ess_threshold": 0.2, "jitter": 0.9}, "PartFilt(N=800, reg=0.9, NER=0.2)", 0.28,
        ),
        TwinConfiguration(
            "L96/EnKF-PertObs-N40", "lorenz96", "EnKF PertObs infl 1.06",
            "Lorenz-96 (40 variables): perturbed-observation EnKF, 40 members, inflation 1.06",
            40, _enkf(perturbed=True, rotate=False), {"inflation": 1.06},
            "EnKF('PertObs', N=40, infl=1.06)", 0.22,
        ),
        TwinConfiguration(
            "L96/EnKF-Sqrt-N24", "lorenz96", "EnKF Sqrt infl 1.013 rot",
            "Lorenz-96 (40 variables): square-root EnKF (random rotation), 24 members, "
            "inflation 1.013; marginal: loses the track in about 4% of 1,001-cycle runs, in "
            "DAPPER too", 24, _enkf(perturbed=False, rotate=True), {"inflation": 1.013},
            "EnKF('Sqrt', N=24, infl=1.013, rot=True)", 0.18,
        ),
    )
}
