"""``random``: the paper's protocol, every not yet measured posture equally likely."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from tofloc.errors import ParameterError
from tofloc.selection.base import SelectionInput, SelectionPolicy

__all__ = ["RandomSelection"]


@dataclass(frozen=True)
class RandomSelection(SelectionPolicy):
    """Uniformly at random among the candidates (no posterior needed).

    In a trial the ``k`` samples are drawn at once, exactly as the protocol always drew
    them (:meth:`draw`, the same call as :func:`evaluation.trials.draw_samples_and_prior`):
    the same seed gives the same samples as before policies existed.
    """

    name: ClassVar[str] = "random"
    uses_posterior: ClassVar[bool] = False

    def scores(self, view: SelectionInput, rng: np.random.Generator) -> NDArray[np.float64]:
        """Independent uniform scores: the best is a uniform choice."""
        return rng.random(len(view.candidates))

    @staticmethod
    def draw(pool: ArrayLike, k: int, rng: np.random.Generator) -> NDArray[np.intp]:
        """``k`` distinct members of ``pool`` at once: ``rng.choice(pool, k, replace=False)``."""
        p = np.asarray(pool, dtype=np.intp)
        if not 1 <= k <= p.size:
            raise ParameterError(f"cannot draw {k} samples from a pool of {p.size}")
        return rng.choice(p, size=k, replace=False).astype(np.intp)
