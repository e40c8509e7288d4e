"""The sensor-model interface: how likely are a problem's frames for each of M base poses?

A :class:`SensorModel` holds validated parameters only. :meth:`SensorModel.bind` does the
per-problem work once (clouds, caches) and returns a :class:`BoundSensorModel` whose
:meth:`~BoundSensorModel.log_likelihood` is vectorized over the M candidate poses.

Two kinds of model (``cumulative``):

* incremental (``False``, the textbook Bayes filter): step ``k`` returns the
  log-likelihood of sample ``k`` alone; a filter adds it to its log-weights;
* cumulative (``True``, the paper's ICP score): step ``k`` scores everything seen so far
  (the merged cloud ``X_k``); a filter replaces its weights with it.
"""

from __future__ import annotations

import dataclasses
import tomllib
from pathlib import Path
from abc import ABC, abstractmethod
from typing import Any, ClassVar, Mapping, TypeVar

import numpy as np
from numpy.typing import NDArray

from tofloc.errors import FormatError, ParameterError
from tofloc.problem import Problem

T = TypeVar("T")

__all__ = ["SensorModel", "BoundSensorModel", "read_model_toml", "params_from_table", "params_from_toml"]

#: Largest sensor-model TOML file we read (bytes).
MAX_TOML_BYTES = 1_000_000


class BoundSensorModel(ABC):
    """A sensor model bound to one problem."""

    #: number of steps (samples) the filter walks through
    n_steps: int

    @abstractmethod
    def log_likelihood(self, poses: NDArray[np.float64], step: int) -> NDArray[np.float64]:
        """Log-likelihood ``(M,)`` of step ``step`` for planar base poses ``(M, 3)``.

        ``-inf`` is allowed (a pose the data excludes); NaN is not.
        """


class SensorModel(ABC):
    """Interface of every sensor-model plug-in (a dataclass of parameters)."""

    name: ClassVar[str] = ""
    cumulative: ClassVar[bool] = False

    @abstractmethod
    def bind(self, problem: Problem) -> BoundSensorModel:
        """Precompute what scoring ``problem`` needs; must not mutate it."""

    def get_params(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)} if dataclasses.is_dataclass(self) else {}


def read_model_toml(path: str | Path) -> dict[str, Any]:
    """Parse a sensor-model TOML file (``tofloc calibrate``'s output), bounded in size;
    every failure is a :class:`FormatError` naming the file."""
    p = Path(path)
    try:
        size = p.stat().st_size
        if size > MAX_TOML_BYTES:
            raise FormatError(p, "file", f"at most {MAX_TOML_BYTES} bytes", f"{size} bytes")
        return tomllib.loads(p.read_text(encoding="utf-8"))
    except OSError as e:
        raise FormatError(p, "file", "a readable TOML file", e.strerror) from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise FormatError(p, "file", "valid TOML", str(e)) from None


def params_from_table(cls: type[T], d: Mapping[str, Any], source: str, table: str) -> T:
    """Build the parameter dataclass ``cls`` from the TOML table ``[table]``: unknown keys
    and out-of-domain values are :class:`FormatError` naming the file and key."""
    known = {f.name for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(set(d) - known)
    if unknown:
        raise FormatError(source, f"[{table}].{unknown[0]}", f"one of {sorted(known)}", "an unknown key")
    try:
        return cls(**dict(d))
    except ParameterError as e:
        raise FormatError(source, f"[{table}]", str(e)) from None


def params_from_toml(cls: type[T], path: str | Path, table: str) -> T:
    """``params_from_table`` on the ``[table]`` of a TOML file (defaults when absent)."""
    p = Path(path)
    data = read_model_toml(p).get(table, {})
    if not isinstance(data, Mapping):
        raise FormatError(p, f"[{table}]", "a table")
    return params_from_table(cls, data, str(p), table)
