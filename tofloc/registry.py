"""Plug-in registry for sensor models and estimators (built-ins plus entry points).

A plug-in is named by a string and points at ``"module:attribute"``. Built-ins are
listed below; third-party packages declare theirs as ``importlib.metadata`` entry
points in the groups ``tofloc.sensor_models``, ``tofloc.estimators`` and
``tofloc.selection_policies``::

    [project.entry-points."tofloc.sensor_models"]
    my_model = "my_package.models:MyModel"

Nothing is imported until a plug-in is asked for (as xarray's backends). A plug-in whose
import fails because a dependency is missing raises :class:`PluginError` with an install
hint when loaded by name; when iterating over all plug-ins (``tofloc list``, the common
check suite), a broken one warns and is skipped.
"""

from __future__ import annotations

import importlib
import importlib.util
import warnings
from dataclasses import dataclass
from importlib import metadata
from typing import Any, Iterator

from tofloc.errors import ParameterError, PluginError, PluginWarning

__all__ = ["PluginSpec", "Registry", "ESTIMATORS", "SENSOR_MODELS", "SELECTION_POLICIES", "loaded_plugins", "get_estimator",
           "get_sensor_model", "registry_for"]

#: pip package to install when an import of this module fails.
_INSTALL_HINTS = {
    "open3d": "pip install open3d  (and the system library libusb-1.0: apt-get install libusb-1.0-0)",
    "gtsam": "pip install gtsam",
    "filterpy": "pip install filterpy",
    "sklearn": "pip install scikit-learn",
    "serial": "pip install pyserial",
    "dask": "pip install 'dask[distributed]'",
    "distributed": "pip install 'dask[distributed]'",
    # modules whose package has another name (a plug-in audit: the hint was `pip install cv2`)
    "yaml": "pip install pyyaml",
    "cv2": "pip install opencv-python",
    "PIL": "pip install pillow",
    "skimage": "pip install scikit-image",
    "sklearn_extra": "pip install scikit-learn-extra",
    "attr": "pip install attrs",
    "jwt": "pip install pyjwt",
    "dateutil": "pip install python-dateutil",
    "bs4": "pip install beautifulsoup4",
    "Crypto": "pip install pycryptodome",
}


@dataclass(frozen=True)
class PluginSpec:
    """Where a plug-in lives: ``target`` is ``"module:attribute"``; ``origin`` is
    ``"builtin"`` or the distribution that declared the entry point."""

    name: str
    target: str
    origin: str = "builtin"


class Registry:
    """Named plug-ins of one kind, loaded lazily.

    Parameters
    ----------
    group : str
        Entry-point group scanned for third-party plug-ins.
    builtins : dict
        ``name -> "module:attribute"`` of the plug-ins shipped with tofloc.
    base : str, optional
        ``"module:Class"`` every plug-in must subclass; its ``name`` class attribute must
        then equal the name it is registered under (checked when it is loaded).
    """

    def __init__(self, group: str, builtins: dict[str, str], base: str | None = None) -> None:
        self.group = group
        self._base = base
        self._specs: dict[str, PluginSpec] = {n: PluginSpec(n, t) for n, t in builtins.items()}
        self._entry_points_scanned = False
        self._cache: dict[str, Any] = {}
        #: entry points not registered because their name was taken (by a built-in, or by
        #: an entry point found earlier on the path): ``(spec, why)``, for ``tofloc list``
        self.ignored: list[tuple[PluginSpec, str]] = []

    def _scan(self) -> None:
        if self._entry_points_scanned:
            return
        self._entry_points_scanned = True
        for ep in metadata.entry_points(group=self.group):  # in the order the import path finds them
            dist = getattr(ep, "dist", None)
            origin = dist.name if dist is not None else "entry point"
            if ep.name in self._specs:
                taken = self._specs[ep.name]
                if taken.target != ep.value:
                    by = "a built-in" if taken.origin == "builtin" else f"{taken.origin} (found first on the import path)"
                    why = f"the name is taken by {by}: {taken.target!r}"
                    self.ignored.append((PluginSpec(ep.name, ep.value, origin), why))
                    warnings.warn(f"{self.group}: entry point {ep.name!r} = {ep.value!r} of {origin} ignored: {why}",
                                  PluginWarning, stacklevel=3)
                continue
            self._specs[ep.name] = PluginSpec(ep.name, ep.value, origin)

    def register(self, name: str, target: str | Any, origin: str = "runtime", *, replace: bool = False) -> None:
        """Register a plug-in at run time: ``target`` is ``"module:attribute"`` or the object itself.

        A name already registered (a built-in, an entry point, an earlier registration) is
        refused unless ``replace`` is True (a plug-in audit: ``register("beam_pf", ...)``
        replaced the built-in without a word, and a wrong string target lost it until the
        first load failed)."""
        self._scan()
        if name in self._specs and not replace:
            raise ParameterError(f"{self.kind} {name!r} is already registered ({self._specs[name].target}, "
                                 f"{self._specs[name].origin}): choose another name, or pass replace=True")
        if isinstance(target, str):
            self._specs[name] = PluginSpec(name, target, origin)
            self._cache.pop(name, None)
        else:
            spec = PluginSpec(name, f"{target.__module__}:{target.__qualname__}", origin)
            self._check(name, spec, target)
            self._specs[name] = spec
            self._cache[name] = target

    def unregister(self, name: str) -> None:
        self._specs.pop(name, None)
        self._cache.pop(name, None)

    def names(self) -> list[str]:
        """Every registered name (nothing imported)."""
        self._scan()
        return sorted(self._specs)

    def spec(self, name: str) -> PluginSpec:
        self._scan()
        try:
            return self._specs[name]
        except KeyError:
            raise PluginError(
                f"unknown {self.kind} {name!r}; available: {', '.join(self.names()) or 'none'}"
            ) from None

    @property
    def kind(self) -> str:
        """What one plug-in is, in words (``"estimator"``, ``"sensor model"``, ``"selection policy"``)."""
        kind = self.group.split(".")[-1]
        return (kind[:-3] + "y" if kind.endswith("ies") else kind.rstrip("s")).replace("_", " ")

    def load(self, name: str) -> Any:
        """Import and return the plug-in's object; :class:`PluginError` with an install hint on failure."""
        if name in self._cache:
            return self._cache[name]
        spec = self.spec(name)
        module_name, _, attr = spec.target.partition(":")
        try:
            module = importlib.import_module(module_name)
        except ModuleNotFoundError as e:
            missing = (e.name or "").split(".")[0]
            if missing and e.name == missing and missing == module_name.split(".")[0]:  # the plug-in's own package
                hint = (f"the target's own package {missing!r} cannot be imported: check the target {spec.target!r} "
                        f"(a typo?) or reinstall what declares it ({spec.origin})")
            elif missing and e.name != missing and importlib.util.find_spec(missing) is not None:
                # the top package is installed, one of its modules is not there: no install fixes that
                hint = (f"{missing!r} is installed but has no module {e.name!r}: check the entry point's target "
                        f"{spec.target!r} (or the plug-in's imports) against that package's version")
            else:
                hint = _INSTALL_HINTS.get(missing, f"install the package that provides it (most often `pip install {missing}`, "
                                                   "though a package's name can differ from its module's)" if missing else "")
            raise PluginError(
                f"{self.kind} {name!r} ({spec.target}, from {spec.origin}) needs the missing module "
                f"{e.name!r}" + (f": {hint}" if hint else "")
            ) from e
        except Exception as e:  # a plug-in's own import error
            raise PluginError(f"{self.kind} {name!r} ({spec.target}, from {spec.origin}) failed to import: {e}") from e
        try:
            obj = module
            for part in attr.split(".") if attr else []:
                obj = getattr(obj, part)
        except AttributeError as e:
            raise PluginError(f"{self.kind} {name!r}: {spec.target} does not exist ({e})") from e
        self._check(name, spec, obj)
        self._cache[name] = obj
        return obj

    def _check(self, name: str, spec: PluginSpec, obj: Any) -> None:
        """The loaded object must be a subclass of the registry's base, named ``name``."""
        if self._base is None:
            return
        mod, _, attr = self._base.partition(":")
        base = getattr(importlib.import_module(mod), attr)
        if not (isinstance(obj, type) and issubclass(obj, base)):
            raise PluginError(f"{self.kind} {name!r} ({spec.target}, from {spec.origin}) is not a subclass of "
                              f"{base.__module__}.{base.__qualname__}")
        declared = getattr(obj, "name", None)
        if declared != name:
            raise PluginError(f"{self.kind} {name!r} ({spec.target}, from {spec.origin}) declares name = {declared!r}: "
                              f"the entry point and the class's name must agree")

    def iter_loaded(self) -> Iterator[tuple[str, Any]]:
        """Every plug-in that loads; a broken one warns and is skipped."""
        for name in self.names():
            try:
                yield name, self.load(name)
            except PluginError as e:
                warnings.warn(f"skipping {self.kind} {name!r}: {e}", PluginWarning, stacklevel=2)

    def status(self) -> list[tuple[PluginSpec, str]]:
        """``(spec, "ok" | error message)`` for every plug-in (imports them)."""
        out = []
        for name in self.names():
            try:
                self.load(name)
                out.append((self.spec(name), "ok"))
            except PluginError as e:
                out.append((self.spec(name), str(e)))
        return out


#: Built-in estimators (name -> class). Each class follows tofloc.problem.Estimator.
ESTIMATORS = Registry(
    "tofloc.estimators",
    {
        "icp_pf": "estimators.particle_filter:ICPScorePF",
        "gtsam_smoother": "estimators.gtsam_smoother:GTSAMSmoother",
        "beam_pf": "estimators.particle_filter:BeamPF",
        "likelihood_field_pf": "estimators.particle_filter:LikelihoodFieldPF",
    },
    base="tofloc.problem:Estimator",
)

#: Built-in sensor models (name -> class). Each follows sensor_models.base.SensorModel.
SENSOR_MODELS = Registry(
    "tofloc.sensor_models",
    {
        "icp_score": "sensor_models.icp_score:ICPScore",
        "beam": "sensor_models.beam:BeamModel",
        "likelihood_field": "sensor_models.likelihood_field:LikelihoodFieldModel",
    },
    base="sensor_models.base:SensorModel",
)


#: Built-in selection policies (name -> class). Each follows tofloc.selection.base.SelectionPolicy.
SELECTION_POLICIES = Registry(
    "tofloc.selection_policies",
    {
        "random": "tofloc.selection.random_policy:RandomSelection",
        "active": "tofloc.selection.active:ActiveSelection",
    },
    base="tofloc.selection.base:SelectionPolicy",
)


def get_estimator(name: str) -> Any:
    """The estimator class registered under ``name``."""
    return ESTIMATORS.load(name)


def get_sensor_model(name: str) -> Any:
    """The sensor-model class registered under ``name``."""
    return SENSOR_MODELS.load(name)


def registry_for(parameter: str) -> Registry | None:
    """The registry whose plug-in a parameter named ``parameter`` selects by name
    (``"sensor_model"`` -> :data:`SENSOR_MODELS`: its ``sensor_model_params`` are that
    plug-in's parameters), or None.

    Parameters
    ----------
    parameter : str
        A parameter name; it matches a registry's :attr:`Registry.kind` with ``_`` for spaces.

    Returns
    -------
    Registry or None
    """
    for registry in (ESTIMATORS, SENSOR_MODELS, SELECTION_POLICIES):
        if registry.kind.replace(" ", "_") == parameter:
            return registry
    return None


def loaded_plugins() -> dict[str, str]:
    """Every plug-in that is not a built-in and that this process has loaded (or registered
    as an object) so far, for a result's
    provenance (:func:`tofloc.provenance.provenance`): ``"<kind> <name>" -> "<target> from
    <distribution> <version>"`` (an entry point's), or ``"... registered at run time"``
    (:meth:`Registry.register`). Empty when only built-ins ran."""
    out: dict[str, str] = {}
    for registry in (ESTIMATORS, SENSOR_MODELS, SELECTION_POLICIES):
        for name in sorted(registry._cache):
            spec = registry._specs.get(name)
            if spec is None or spec.origin == "builtin":
                continue
            if spec.origin == "runtime":
                where = "registered at run time"
            else:
                try:
                    where = f"from {spec.origin} {metadata.version(spec.origin)}"
                except (metadata.PackageNotFoundError, ValueError):
                    where = f"from {spec.origin} (version unknown)"
            out[f"{registry.kind} {name}"] = f"{spec.target} {where}"
    return out
