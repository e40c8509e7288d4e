"""The sensor-model interface: how likely are a problem's frames for each of M states?

A :class:`SensorModel` holds validated parameters only. :meth:`SensorModel.bind` does the
per-problem work once (rays, clouds, caches) and returns a :class:`BoundSensorModel`
whose :meth:`~BoundSensorModel.log_likelihood` is vectorized over M candidate states.

The state
---------
A state is the planar base pose ``(x, y, yaw)`` followed by the nuisance variables the
bound model declares in :attr:`BoundSensorModel.state` (column 3, 4, ... in that order).
A model lists the nuisances it *can* estimate (:attr:`SensorModel.nuisances`, e.g. the
support's rotation and a range scale); it declares one only when the problem declares
its prior (:attr:`tofloc.problem.Problem.nuisance`: the rig's tolerances or a
calibration's uncertainty, :func:`declared_state`). A filter builds its particle columns
from the declaration; nothing is positional by convention.

How a step enters the weights (:attr:`SensorModel.weight_update`)
-----------------------------------------------------------------
* ``"bayes"`` (the textbook Bayes filter): step ``k`` returns the log-likelihood of
  sample ``k`` alone; a filter adds it to its log-weights.
* ``"replace"`` (the paper's ICP score): step ``k`` returns a log-score of everything seen
  so far (the merged cloud ``X_k``); a filter replaces its log-weights with it.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any, ClassVar, Literal, Mapping, Sequence

import numpy as np
from numpy.typing import NDArray

from tofloc.errors import ParameterError, PluginError
from tofloc.problem import Problem

__all__ = ["check_bool_or_auto", "held_states", "place_correlation_of", "NUISANCES", "WEIGHT_UPDATES", "CHUNK_BYTES", "StateVariable", "SensorModel", "BoundSensorModel", "declared_state", "reference_pose", "place_weights", "direction_places", "PLACE_PARAM_BOUNDS", "check_place_params", "built_from_scans"]

#: Nuisance variables a model may estimate, with their unit.
NUISANCES = {"support_yaw": "rad", "range_scale": "1"}
WEIGHT_UPDATES = ("bayes", "replace")
#: Roughening floor of a nuisance column, as a fraction of its prior sigma.
JITTER_FLOOR_FRACTION = 0.01
#: Temporaries one :meth:`BoundSensorModel.log_likelihood_chunked` call may hold (bytes).
CHUNK_BYTES = 128 * 2**20
#: Default upper estimate of the temporaries a model makes per state and per zone (or
#: sub-ray): ~32 float64 arrays of the zones' shape.
TEMP_BYTES_PER_ZONE = 256
#: :meth:`BoundSensorModel.fitted_noise_scale`: the largest scale it fits (times the model's),
#: its iterations, their relative tolerance, and the least rise that counts.
REFIT_SIGMA_MAX = 3.0
REFIT_SIGMA_ITERATIONS = 100
REFIT_SIGMA_TOLERANCE = 1e-4
REFIT_SIGMA_MIN_RISE = 0.05


@dataclass(frozen=True)
class StateVariable:
    """A variable a bound model estimates beyond ``(x, y, yaw)``.

    Parameters
    ----------
    name : str
        One of :data:`NUISANCES`.
    sigma : float
        Prior standard deviation (the prior is centred on 0: the problem's rig and range
        model are already the best description).
    jitter_floor : float
        Smallest roughening jitter a particle filter gives the column.
    source : str
        Where the prior came from (``"rig tolerance"``, ``"calibration"``).
    """

    name: str
    sigma: float
    jitter_floor: float
    source: str = ""

    def log_prior(self, value: float) -> float:
        """Log density of the variable's prior, ``N(0, sigma^2)``, at ``value``."""
        return -0.5 * (value / self.sigma) ** 2 - math.log(math.sqrt(2.0 * math.pi) * self.sigma)

    def __post_init__(self) -> None:
        if self.name not in NUISANCES:
            raise ValueError(f"unknown state variable {self.name!r}: expected one of {sorted(NUISANCES)}")
        if not (np.isfinite(self.sigma) and self.sigma > 0 and np.isfinite(self.jitter_floor) and self.jitter_floor >= 0):
            raise ValueError(f"state variable {self.name}: sigma must be > 0 and jitter_floor >= 0")


def declared_state(problem: Problem, supported: tuple[str, ...]) -> tuple[StateVariable, ...]:
    """The nuisances a model supporting ``supported`` estimates on ``problem``: those the
    problem declares (:attr:`tofloc.problem.NuisancePriors.declared`), in that order."""
    out = []
    for name in problem.nuisance.declared:
        if name in supported:
            sigma = problem.nuisance.sigma(name)
            out.append(StateVariable(name, sigma, JITTER_FLOOR_FRACTION * sigma, getattr(problem.nuisance, f"{name}_source")))
    return tuple(out)


def reference_pose(states: NDArray[np.float64]) -> NDArray[np.float64]:
    """One planar pose ``(3,)`` standing for states ``(M, 3 + n)``: the median x and y and
    the circular mean of the yaw (where per-zone quantities that vary slowly with the
    pose, such as a configuration's effect on a reading, are evaluated once for all)."""
    x = np.asarray(states, dtype=float)
    return np.array([np.median(x[:, 0]), np.median(x[:, 1]), np.arctan2(np.mean(np.sin(x[:, 2])), np.mean(np.cos(x[:, 2])))])


def held_states(poses: NDArray[np.float64], values: Sequence[float]) -> NDArray[np.float64]:
    """Filter states ``(M, 3 + n)``: planar poses ``(M, 3)`` with each declared nuisance
    held at one of ``values`` (``n`` of them, in the model's column order); the poses as
    they are when there is none."""
    P = np.atleast_2d(np.asarray(poses, dtype=float))
    return np.column_stack([P] + [np.full(P.shape[0], float(x)) for x in values]) if len(values) else P


def check_bool_or_auto(name: str, value: object) -> None:
    """Refuse a parameter that must be True, False or ``"auto"`` (decided per problem by
    :meth:`SensorModel.for_problem`), naming it."""
    if not (isinstance(value, bool) or (isinstance(value, str) and value == "auto")):
        raise ParameterError(f"{name} must be true, false or \"auto\", got {value!r}")


#: Bounds of ``place_correlation`` and ``place_radius`` (m), for every model that weighs places.
PLACE_PARAM_BOUNDS = (("place_correlation", 0.0, 1.0), ("place_radius", 0.005, 1.0))


def check_place_params(owner: Any, prefix: str = "") -> None:
    """Refuse an ``owner``'s ``place_correlation`` or ``place_radius`` outside
    :data:`PLACE_PARAM_BOUNDS` (or not a finite number), naming it as ``prefix + name``
    (the beam and likelihood-field models and the smoother share the check)."""
    for n, lo, hi in PLACE_PARAM_BOUNDS:
        check_in_range(getattr(owner, n), prefix + n, lo, hi)


def check_in_range(v: Any, name: str, lo: float, hi: float) -> None:
    """Refuse ``v`` unless it is a finite number in ``[lo, hi]`` (not a bool), naming
    ``name``: ``"beam.unknown_weight must be in [0, 1], got 2"``."""
    if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v) or not lo <= v <= hi:
        raise ParameterError(f"{name} must be in [{lo}, {hi}], got {v!r}")


def built_from_scans(problem: Problem) -> bool:
    """Whether ``problem``'s map was built from scans: it carries its known space
    (:attr:`tofloc.maps.Map.known_space`, as the nano-swarm importer's maps do). What
    ``refit_correlation = "auto"`` decides on, for the sensor models and the smoother alike."""
    return getattr(problem.map, "known_space", None) is not None


def place_weights(points: list[NDArray[np.float64]], radius: float, rho: float) -> list[NDArray[np.float64] | None]:
    """Per sample, each end point's weight ``1 / (1 + n rho)``, ``n`` the end points of
    EARLIER samples within ``radius`` of it in the plane of ``points`` (per sample
    ``(P_k, 3)``, the base frame at the configurations): Kish's design effect for a place
    read again by later samples, whose residuals share the map's error there (correlation
    ``rho``). The first sample to see a place counts fully; neighbouring zones of one sample
    are different parts of a wall and count fully too (counting them as well cost the
    simulator 1.4-2.8x more RMSE, docs/sensor-models.md). Only earlier samples: a sample's
    weights do not depend on later ones (a filter's answer after k samples reads off a
    longer pass). All None when ``rho`` is 0."""
    if rho <= 0 or not points:
        return [None] * len(points)
    from scipy.spatial import cKDTree

    out: list[NDArray[np.float64] | None] = []
    seen = np.zeros((0, 2))
    for p in points:
        xy = np.asarray(p, dtype=float)[:, :2]
        n = cKDTree(seen).query_ball_point(xy, radius, return_length=True) if seen.shape[0] and xy.shape[0] else np.zeros(xy.shape[0])
        out.append(1.0 / (1.0 + rho * np.asarray(n, dtype=float)))
        seen = np.vstack([seen, xy])
    return out


def direction_places(dirs: NDArray[np.float64], mask: NDArray[np.bool_], zone_width: NDArray[np.float64],
                     radius: float) -> list[NDArray[np.float64]]:
    """Places for readings without an end point (a zone with no return): per sample ``k``
    the masked zones' directions, ``dirs`` ``(K, S, Z, 3)`` in the base frame at the
    configurations, as points ``(P_k, 3)``: the unit direction's x, y times
    ``radius / (zone_width[s] / 2)``, z = 0, with ``zone_width`` ``(S,)`` each sensor's zone
    angle (rad). Two horizontal directions within about half a zone of each other lie
    within ``radius`` (zones whose footprints mostly overlap, as :func:`place_weights`
    reads them); an inclined direction comes nearer the centre by the cosine of its
    elevation, so that rays looking up or down share a place and one looking 60 deg up is
    far from a horizontal one (the beam model's no-return zones, docs/sensor-models.md,
    "Zones with no return")."""
    d = np.asarray(dirs, dtype=float)
    n = np.linalg.norm(d, axis=-1, keepdims=True)
    scale = float(radius) / (0.5 * np.asarray(zone_width, dtype=float))  # (S,)
    xy = (d / np.maximum(n, 1e-12))[..., :2] * scale[None, :, None, None]
    pts = np.concatenate([xy, np.zeros(xy.shape[:-1] + (1,))], axis=-1)
    m = np.asarray(mask, dtype=bool)
    return [pts[k][m[k]] for k in range(pts.shape[0])]


def place_correlation_of(residuals: list[NDArray[np.float64]], points: list[NDArray[np.float64]],
                         radius: float) -> float | None:
    """The correlation of normalized residuals at one place: per sample ``k`` the residuals
    ``(P_k,)`` (in hit sigmas) of its end points ``(P_k, 3)`` (base frame at the
    configurations); over the pairs of end points of DIFFERENT samples within ``radius`` of
    each other in the plane, ``sum r_i r_j / sqrt(sum r_i^2 sum r_j^2)`` with the residuals
    clipped to +-3 (NaN as 0), clipped to [0, 1]; None below 0.05 (no change) or without such
    pairs. Uncentered on purpose: a place where the map is off by the same amount for every
    sample that sees it is the correlation this measures (``refit_correlation`` of the
    likelihood field and the beam model; docs/sensor-models.md, "Correlated places")."""
    from scipy.spatial import cKDTree

    if not residuals:
        return None
    r = np.concatenate([np.clip(np.nan_to_num(np.asarray(x, dtype=float), nan=0.0), -3.0, 3.0) for x in residuals])
    pts = np.concatenate([np.asarray(x, dtype=float)[:, :2] for x in points])
    smp = np.concatenate([np.full(np.asarray(x).shape[0], k) for k, x in enumerate(points)])
    if r.shape[0] != pts.shape[0]:
        raise ValueError(f"place_correlation_of: {r.shape[0]} residuals for {pts.shape[0]} end points")
    pairs = cKDTree(pts).query_pairs(radius, output_type="ndarray")
    pairs = pairs[smp[pairs[:, 0]] != smp[pairs[:, 1]]]
    if pairs.shape[0] == 0:
        return None
    a, b = r[pairs[:, 0]], r[pairs[:, 1]]
    den = math.sqrt(float(a @ a) * float(b @ b))
    rho = min(max(float(a @ b) / den, 0.0), 1.0) if den > 0 else 0.0
    return rho if rho >= 0.05 else None


class BoundSensorModel(ABC):
    """A sensor model bound to one problem."""

    #: number of steps (samples) a filter walks through
    n_steps: int
    #: the variables estimated beyond (x, y, yaw), in column order from 3
    state: tuple[StateVariable, ...] = ()

    @abstractmethod
    def log_likelihood(self, states: NDArray[np.float64], step: int) -> NDArray[np.float64]:
        """Log-likelihood ``(M,)`` of step ``step`` for states ``(M, 3 + len(state))``.

        ``-inf`` is allowed (a state the data exclude); NaN is not.
        """

    def derived_params(self) -> dict[str, Any]:
        """The model parameters this binding chose from the problem's data (name -> value;
        e.g. the likelihood field's ``r_field`` from the zones' sigmas): the model with them
        set (``dataclasses.replace``) binds any problem as this binding did. A binding to
        the first k samples of a problem may choose differently from one to all of them, so
        a filter that reads the answer after k samples off a longer pass fixes them first
        (:meth:`estimators.particle_filter.ParticleFilter.estimate_prefixes`). A plug-in
        model that derives parameters from the data must name them here. Default: none."""
        return {}

    def refit(self, state: NDArray[np.float64]) -> "SensorModel | None":
        """A model whose data-dependent parameters are fitted to this problem's own readings
        at ``state`` ``(3 + len(state),)`` (a first estimate), or None when the model fits
        nothing or the fit leaves it unchanged. A filter that gets a model runs again with
        it (:class:`estimators.particle_filter.ParticleFilter`). Default: None."""
        return None

    def data_fit(self, state: NDArray[np.float64]) -> bool:
        """Whether the problem's data fit its map at ``state`` ``(3 + len(state),)``
        (:func:`tofloc.fit_check.check_pose`, the shared fit check, with the state's support
        yaw and range scale): where they do not, a first estimate is likely wrong, and a
        refit there would explain the misfit as unmapped objects or as noise."""
        from tofloc.fit_check import check_pose

        x = np.asarray(state, dtype=float)
        nuisance = {v.name: float(x[3 + i]) for i, v in enumerate(self.state)}
        problem = getattr(self, "problem")
        return bool(check_pose(problem, x[:3], nuisance.get("support_yaw", 0.0), nuisance.get("range_scale", 0.0)).ok)

    def hit_terms(self, states: NDArray[np.float64], step: int) -> tuple[NDArray[np.float64], ...] | None:
        """For a model with a Gaussian hit density and a ``sigma_scale`` parameter: at
        ``states`` ``(M, 3 + n)`` and sample ``step``, every zone's (or end point's)
        probability ``p``, the part of it from the hit Gaussian (0 where the zone has no
        valid reading) and the reading's residual in hit sigmas, each ``(M, ...)``; None
        when the sample has nothing to fit. Models without one raise NotImplementedError."""
        raise NotImplementedError(f"{type(self).__name__} has no hit density to fit a noise scale to")

    def unit_log_likelihoods(self, states: NDArray[np.float64], step: int
                             ) -> tuple[NDArray[np.float64], NDArray[np.float64]] | None:
        """Sample ``step``'s log-likelihood split into its units (zones, or end points): at
        ``states`` ``(M, 3 + n)`` each unit's untempered log-probability times its weight
        (``place_correlation``), ``(M, U)``, which sum, times ``temper``, to
        :meth:`log_likelihood` (to rounding); and each unit's place ``(U, 2)``: x, y in the
        base frame at the configurations, where the unit looked (the same for every state).
        A test that weighs two poses zone by zone, with zones of one place counted as one
        cluster, needs both (:mod:`estimators.basin_check`). None (the default): the model
        does not split its likelihood."""
        return None

    def places(self) -> list[NDArray[np.float64]] | None:
        """Per sample, the end points ``(P_k, 3)`` whose residuals :meth:`place_residuals`
        gives, in the base frame at the configurations (the places of a model's
        ``place_correlation``); None (the default) when the model has none."""
        return None

    def place_residuals(self, residuals: NDArray[np.float64], step: int) -> NDArray[np.float64]:
        """Sample ``step``'s residuals in hit sigmas from :meth:`hit_terms` (one state's),
        in the order of :meth:`places` (default: as they come)."""
        return residuals

    def fitted_place_correlation(self, state: NDArray[np.float64]) -> float | None:
        """The correlation of the problem's residuals in hit sigmas (:meth:`hit_terms`) at
        ``state`` over pairs of end points (:meth:`places`) of different samples within the
        model's ``place_radius`` of each other (:func:`place_correlation_of`: uncentered,
        clipped to [0, 1]; None below 0.05, without such pairs, or without places): what
        ``refit_correlation`` fits."""
        places = self.places()
        if places is None:
            return None
        radius = getattr(getattr(self, "model", None), "place_radius", None)
        if radius is None:
            raise NotImplementedError(f"{type(self).__name__} has places() but its model has no place_radius "
                                      "(the radius, in metres, within which end points are one place)")
        x = np.asarray(state, dtype=float)[None]
        res, pts = [], []
        for k in range(self.n_steps):
            t = self.hit_terms(x, k)
            if t is None:
                continue
            res.append(self.place_residuals(t[2][0], k))
            pts.append(places[k])
        return place_correlation_of(res, pts, float(radius))

    def hit_moments(self, state: NDArray[np.float64]) -> tuple[float, float]:
        """Over every sample's zones at ``state`` ``(3 + n,)`` (:meth:`hit_terms`): the hit
        component's responsibilities ``w = hit / p`` summed, and ``w t^2`` summed (``t`` the
        residual in hit sigmas): the E step of :meth:`fitted_noise_scale`."""
        x = np.asarray(state, dtype=float)[None]
        total_w = total_wt2 = 0.0
        for k in range(self.n_steps):  # a loop over samples (<= tens), each vectorized over zones
            terms = self.hit_terms(x, k)
            if terms is None:
                continue
            p, hit, t = (np.asarray(a)[0] for a in terms)
            w = hit / np.maximum(p, 1e-300)
            total_w += float(w.sum())
            total_wt2 += float(np.sum(np.where(w > 0, w * (t * t), 0.0)))  # zones without a reading: w = 0, t undefined
        return total_w, total_wt2

    def fitted_noise_scale(self, state: NDArray[np.float64]) -> float | None:
        """The noise scale (``sigma_scale``, which multiplies the hit density's sigma) that
        the problem's own readings give at ``state``, by EM: each iteration multiplies it by
        the root of :meth:`hit_moments`' weighted mean squared residual, clipped to [the
        model's ``sigma_scale``, :data:`REFIT_SIGMA_MAX` times it], to
        :data:`REFIT_SIGMA_TOLERANCE` (at most :data:`REFIT_SIGMA_ITERATIONS` times). None
        when it would not rise by more than :data:`REFIT_SIGMA_MIN_RISE` or where the data
        do not fit the map at ``state`` (:meth:`data_fit`). The bound model is expected to
        have a ``model`` attribute (a dataclass with ``sigma_scale``) that its
        :meth:`hit_terms` reads."""
        model = getattr(self, "model")
        start = float(model.sigma_scale)
        if not self.data_fit(state):
            return None
        work = copy.copy(self)  # the same bound data, its model's scale replaced at each iteration
        scale = start
        for _ in range(REFIT_SIGMA_ITERATIONS):
            w, wt2 = work.hit_moments(state)
            if not w > 0:
                return None
            new = min(max(scale * math.sqrt(wt2 / w), start), REFIT_SIGMA_MAX * start)
            moved = abs(new - scale)
            scale = new
            work.model = dataclasses.replace(model, sigma_scale=scale)  # type: ignore[attr-defined]
            if moved < REFIT_SIGMA_TOLERANCE * scale:
                break
        return scale if scale > (1.0 + REFIT_SIGMA_MIN_RISE) * start else None

    def temporaries_per_state(self) -> int:
        """Upper estimate of the bytes of temporaries :meth:`log_likelihood` makes per state.

        Default: :data:`TEMP_BYTES_PER_ZONE` times the zones of the bound problem's rig
        (attribute ``problem``), times the sub-rays per zone of its ray caster when the model
        has one (attribute ``rays``, a :class:`tofloc.zone_caster.PlanarZoneRays`). Models
        override it when they know better."""
        problem = getattr(self, "problem", None)
        zones = problem.rig.n_sensors * problem.rig.n_zones if problem is not None else 1
        caster = getattr(getattr(self, "rays", None), "caster", None)
        return TEMP_BYTES_PER_ZONE * zones * int(getattr(caster, "n_sub", 1))

    def reserved_temporaries(self) -> int:
        """Bytes of temporaries :meth:`log_likelihood` may hold whatever the number of states
        (a piece size of its own, e.g. the beam model's rough footprints,
        :data:`tofloc.zone_caster.FOOTPRINT_PIECE_BYTES`): :meth:`log_likelihood_chunked`
        sizes its chunks from what is left. Default: 0."""
        return 0

    def log_likelihood_chunked(self, states: NDArray[np.float64], step: int,
                               max_bytes: int = CHUNK_BYTES) -> NDArray[np.float64]:
        """:meth:`log_likelihood` of the states in chunks whose temporaries stay under
        ``max_bytes`` (:meth:`temporaries_per_state` per state plus :meth:`reserved_temporaries`), whatever the number of states and
        zones: the same numbers (each state's value is computed alone), bounded memory.
        What a filter calls. (One exception: a configuration covariance's per-zone variance
        is evaluated once per call at :func:`reference_pose` of the states given, so with
        a covariance and more states than one chunk holds, each chunk uses its own
        reference; with one ray per zone and up to 500 zones, or the beam model's footprints on
        rough zones and up to 390 zones, one chunk holds 1000 states.)"""
        M = states.shape[0]
        chunk = max(1, (int(max_bytes) - self.reserved_temporaries()) // max(1, self.temporaries_per_state()))
        if M <= chunk:
            return checked_log_likelihood(self, self.log_likelihood(states, step), M, step)
        return np.concatenate([checked_log_likelihood(self, self.log_likelihood(states[a : a + chunk], step),
                                                      min(chunk, M - a), step) for a in range(0, M, chunk)])

    def column(self, states: NDArray[np.float64], name: str) -> NDArray[np.float64] | None:
        """The ``(M,)`` column of nuisance ``name`` in ``states``, or None when not declared."""
        for i, v in enumerate(self.state):
            if v.name == name:
                return states[:, 3 + i]
        return None


def checked_log_likelihood(bound: object, ll: object, n_states: int, step: int) -> NDArray[np.float64]:
    """``ll``, what ``bound.log_likelihood(states, step)`` returned for ``n_states`` states,
    as a float64 array, or :class:`~tofloc.errors.PluginError` naming the binding's class
    when it breaks the contract of :meth:`BoundSensorModel.log_likelihood`: a float numpy
    array shaped ``(n_states,)``, no NaN, no ``+inf`` (``-inf`` excludes a state). What the
    filters call (through :meth:`BoundSensorModel.log_likelihood_chunked`) and what the
    common check suite asserts (:func:`tofloc.testing.check_model_output_shape`), so a
    plug-in that passes the checks is not refused by a filter."""
    where = (f"sensor model binding {type(bound).__module__}.{type(bound).__qualname__}: "
             f"log_likelihood(states, step={step}) of {n_states} states")
    expected = f"a float numpy array shaped ({n_states},) with no NaN and no +inf (-inf excludes a state)"
    if not isinstance(ll, np.ndarray):
        raise PluginError(f"{where} returned a {type(ll).__name__}; expected {expected}")
    if ll.dtype.kind != "f":
        raise PluginError(f"{where} returned an array of dtype {ll.dtype}; expected {expected}")
    if ll.shape != (n_states,):
        raise PluginError(f"{where} returned an array shaped {ll.shape}; expected {expected}")
    bad = int(np.count_nonzero(np.isnan(ll))), int(np.count_nonzero(np.isposinf(ll)))
    if bad[0] or bad[1]:
        raise PluginError(f"{where} returned {bad[0]} NaN and {bad[1]} +inf values; expected {expected}")
    return ll.astype(np.float64, copy=False)


def bind_checked(model: "SensorModel", problem: Problem) -> BoundSensorModel:
    """``model.bind(problem)``, or :class:`~tofloc.errors.PluginError` naming the model when
    the plug-in returns something other than a :class:`BoundSensorModel`."""
    bound = model.bind(problem)
    if not isinstance(bound, BoundSensorModel):
        raise PluginError(f"sensor model {model.name!r} ({type(model).__module__}.{type(model).__qualname__}): "
                          f"bind(problem) returned a {type(bound).__name__}; expected an instance of a subclass of "
                          "sensor_models.base.BoundSensorModel")
    return bound


class SensorModel(ABC):
    """Interface of every sensor-model plug-in (a dataclass of parameters)."""

    #: registry name
    name: ClassVar[str] = ""
    #: how a step's value enters a particle filter's weights (see the module doc)
    weight_update: ClassVar[Literal["bayes", "replace"]] = "bayes"
    #: nuisances this model can estimate (it declares those the problem declares)
    nuisances: ClassVar[tuple[str, ...]] = ()
    #: whether its scores depend on the problem's range model or calibrated mounting
    uses_calibration: ClassVar[bool] = True

    @classmethod
    def check_calibration_table(cls, table: Mapping[str, Any], source: str) -> None:
        """Refuse a calibration file's table for this model (``[NAME]``) when it is unusable,
        as the file is read rather than at the first estimate: a
        :class:`tofloc.errors.FormatError` naming ``source`` and the table. Default: every
        table is accepted here (the model checks it when it binds)."""
        return None

    def calibration_footprint(self) -> int:
        """Sub-rays per zone side this model casts a zone with (its calibration must be fitted
        with the same, :meth:`tofloc.problem.Estimator.calibration_footprint`). Default: 1."""
        return 1

    @abstractmethod
    def bind(self, problem: Problem) -> BoundSensorModel:
        """Precompute what scoring ``problem`` needs; must not mutate it."""

    def for_problem(self, problem: Problem) -> "SensorModel":
        """This model with its data-dependent defaults decided for ``problem``.

        ``refit_correlation = "auto"`` (beam, likelihood field) becomes True on a map built
        from scans (one that carries its known space, :attr:`tofloc.maps.Map.known_space`,
        as the nano-swarm importer's maps do): such a map's errors are places, a wall it
        lacks or misplaces, that every sample seeing the place meets again, so the zones'
        errors there are correlated and the correlation is fitted from the problem's own
        residuals; on any other map (a CAD mesh, the simulator's scenes) False. Every
        other model is returned as it is. :meth:`bind` applies it, and so does a filter
        before it asks :meth:`refits`."""
        if getattr(self, "refit_correlation", None) == "auto" and dataclasses.is_dataclass(self):
            return dataclasses.replace(self, refit_correlation=built_from_scans(problem))  # type: ignore[type-var]
        return self

    def refits(self) -> bool:
        """Whether its bound model may refit itself to a problem's readings at a first
        estimate (:meth:`BoundSensorModel.refit`): a filter's answer after k samples then
        depends on those k samples' refit, and cannot be read off one pass over more
        samples (:meth:`estimators.particle_filter.ParticleFilter.estimate_prefixes`).
        Default: any of the parameters ``refit_short``, ``refit_sigma``, ``refit_correlation`` set
        (an undecided ``"auto"`` counts: decide it first with :meth:`for_problem`)."""
        return any(bool(getattr(self, n, False)) for n in ("refit_short", "refit_sigma", "refit_correlation"))

    def get_params(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)} if dataclasses.is_dataclass(self) else {}
