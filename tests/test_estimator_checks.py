"""The common check suite (tofloc.testing) over EVERY registered estimator, plug-ins too."""

from __future__ import annotations

import warnings

from tofloc.registry import ESTIMATORS
from tofloc.testing import parametrize_with_checks

#: Smaller-than-default settings so that the suite stays fast; each estimator keeps its
#: own algorithm. Estimators not listed run with their defaults.
FAST_PARAMS: dict[str, dict] = {
    "icp_pf": {"n_particles": 400},
    "gtsam_smoother": {"n_starts": 2, "n_candidates": 50},
    "beam_pf": {"n_particles": 300},
    "likelihood_field_pf": {"n_particles": 300},
}


def _registered():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        loaded = list(ESTIMATORS.iter_loaded())
    return [cls(**FAST_PARAMS.get(name, {})) for name, cls in loaded]


@parametrize_with_checks(_registered())
def test_registered_estimators(estimator, check) -> None:
    check(estimator)


def test_every_registered_estimator_is_checked() -> None:
    names = {e.name for e in _registered()}
    assert {"icp_pf"} <= names
    assert names == set(ESTIMATORS.names())
