"""Where a map built from scans knows anything: its *known space*.

A CAD model describes everything; a map made from scans only describes what its scans
saw. Outside that (behind walls, round corners nobody looked past, corridors nobody flew)
the map holds no wall, but not because there is none: it does not know. A sensor model
that reads "no wall in the map" as "no wall" pulls the pose toward where the map happens
to explain more zones (docs/sensor-models.md, "Unknown space").

:class:`KnownSpace` is a 2-D grid over the map's x-y plane, valid for heights
``z_range``: a cell is *known* when a scan's ray crossed it (seen free) or ended in it (a
wall); every other cell, and every height outside ``z_range``, is unknown. The map
builder that carved the free space writes it
(:func:`tofloc.scan_maps.known_cells`); it travels with the map file as a sidecar
``<map stem>.known.npz`` that :meth:`tofloc.maps.Map.load` attaches when present.

File format (``.known.npz``, read with ``allow_pickle=False``): ``format`` (the string
``"tofloc-known-space-v1"``), ``origin`` (2,) float64 (x, y of the grid's corner, m),
``cell`` () float64 (m), ``z_range`` (2,) float64 (m), ``known`` (nx, ny) uint8 (1 known,
0 unknown; at most :data:`MAX_CELLS` cells).
"""

from __future__ import annotations

import math
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from tofloc.atomic import atomic_path
from tofloc.errors import FormatError, ParameterError

__all__ = ["FORMAT", "MAX_CELLS", "KnownSpace", "sidecar_path"]

FORMAT = "tofloc-known-space-v1"
#: Largest grid a file may hold.
MAX_CELLS = 64_000_000
#: Largest sidecar file (bytes).
MAX_FILE_BYTES = 256 * 1024 * 1024


def sidecar_path(map_path: str | Path) -> Path:
    """``maps/walls.ply`` -> ``maps/walls.known.npz``."""
    p = Path(map_path)
    return p.with_name(p.stem + ".known.npz")


@dataclass(frozen=True, eq=False)
class KnownSpace:
    """A 2-D grid of known cells (see the module docstring).

    Attributes
    ----------
    origin : ndarray (2,)
        x, y of the corner of cell (0, 0) (m).
    cell : float
        Cell side (m).
    z_range : ndarray (2,)
        Heights (m) the grid describes; outside, everything is unknown.
    known : ndarray of bool (nx, ny)
    """

    origin: NDArray[np.float64]
    cell: float
    z_range: NDArray[np.float64]
    known: NDArray[np.bool_]

    def __post_init__(self) -> None:
        o = np.asarray(self.origin, dtype=float).reshape(-1)
        z = np.asarray(self.z_range, dtype=float).reshape(-1)
        k = np.asarray(self.known)
        if o.shape != (2,) or not np.isfinite(o).all():
            raise ParameterError(f"known space: origin must be 2 finite numbers, got {self.origin!r}")
        if not (isinstance(self.cell, (int, float)) and math.isfinite(self.cell) and 1e-3 <= self.cell <= 10.0):
            raise ParameterError(f"known space: cell must be in [0.001, 10] m, got {self.cell!r}")
        if z.shape != (2,) or not np.isfinite(z).all() or z[0] > z[1]:
            raise ParameterError(f"known space: z_range must be two finite heights lo <= hi, got {self.z_range!r}")
        if k.ndim != 2 or k.size == 0 or k.size > MAX_CELLS:
            raise ParameterError(f"known space: known must be a non-empty 2-D grid of at most {MAX_CELLS} cells, got shape {k.shape}")
        kb = k.astype(bool)
        kb.setflags(write=False)
        o.setflags(write=False)
        z.setflags(write=False)
        object.__setattr__(self, "origin", o)
        object.__setattr__(self, "z_range", z)
        object.__setattr__(self, "known", kb)
        object.__setattr__(self, "cell", float(self.cell))

    # -- queries -------------------------------------------------------------------------------
    def is_known(self, points: ArrayLike) -> NDArray[np.bool_]:
        """Whether points ``(..., 3)`` lie in known space (outside the grid or the heights: no)."""
        p = np.asarray(points, dtype=float)
        ij = np.floor((p[..., :2] - self.origin) / self.cell).astype(np.int64)
        nx, ny = self.known.shape
        inside = (ij[..., 0] >= 0) & (ij[..., 0] < nx) & (ij[..., 1] >= 0) & (ij[..., 1] < ny)
        inside &= (p[..., 2] >= self.z_range[0]) & (p[..., 2] <= self.z_range[1])
        i = np.where(inside, ij[..., 0], 0)
        j = np.where(inside, ij[..., 1], 0)
        return inside & self.known[i, j]

    def unknown_entry(self, origins: ArrayLike, directions: ArrayLike, max_t: ArrayLike) -> NDArray[np.float64]:
        """Distance along each ray to where it first enters unknown space (``inf`` when it
        stays in known space up to ``max_t``), sampled every half cell.

        Parameters
        ----------
        origins : array (..., 3)
        directions : array (..., 3)
            Unit directions (broadcast against ``origins``).
        max_t : array (...)
            How far to look along each ray (m).
        """
        o = np.asarray(origins, dtype=float)
        d = np.asarray(directions, dtype=float)
        tmax = np.asarray(max_t, dtype=float)
        shape = np.broadcast_shapes(o.shape[:-1], d.shape[:-1], tmax.shape)
        o = np.broadcast_to(o, shape + (3,)).reshape(-1, 3)
        d = np.broadcast_to(d, shape + (3,)).reshape(-1, 3)
        tm = np.broadcast_to(tmax, shape).reshape(-1)
        out = np.full(o.shape[0], np.inf)
        finite = np.isfinite(tm) & (tm > 0)
        if not finite.any():
            return out.reshape(shape)
        step = self.cell / 2.0
        n_steps = int(math.ceil(float(tm[finite].max()) / step)) + 1
        todo = np.flatnonzero(finite)
        chunk = max(1, 4_000_000 // n_steps)  # bounded temporaries, each chunk vectorized
        for a in range(0, todo.size, chunk):
            idx = todo[a:a + chunk]
            t = (np.arange(n_steps) * step)[None, :]
            q = o[idx, None, :] + t[..., None] * d[idx, None, :]
            unknown = ~self.is_known(q) & (t <= tm[idx, None])
            first = np.argmax(unknown, axis=1)
            hit = unknown[np.arange(idx.size), first]
            out[idx] = np.where(hit, first * step, np.inf)
        return out.reshape(shape)

    # -- identity and files --------------------------------------------------------------------
    def fingerprint_bytes(self) -> bytes:
        """Bytes that identify the grid (for :meth:`tofloc.maps.Map.fingerprint`)."""
        head = np.concatenate([self.origin, [self.cell], self.z_range]).tobytes() + np.asarray(self.known.shape, np.int64).tobytes()
        return FORMAT.encode() + head + np.packbits(self.known).tobytes()

    def save(self, path: str | Path) -> Path:
        """Write the grid (atomically) to ``path`` (``.known.npz``)."""
        import io

        buf = io.BytesIO()
        np.savez_compressed(buf, format=np.array(FORMAT), origin=self.origin, cell=np.array(self.cell),
                            z_range=self.z_range, known=self.known.astype(np.uint8))
        with atomic_path(path) as tmp:
            Path(tmp).write_bytes(buf.getvalue())
        return Path(path)

    @classmethod
    def load(cls, path: str | Path) -> "KnownSpace":
        """Read a ``.known.npz`` file; anything unexpected raises :class:`FormatError` naming the file and entry."""
        p = Path(path)
        try:
            size = p.stat().st_size
        except OSError as e:
            raise FormatError(p, "file", "an existing readable file", e.strerror or type(e).__name__) from None
        if size > MAX_FILE_BYTES:
            raise FormatError(p, "file", f"at most {MAX_FILE_BYTES} bytes", size)
        try:
            with zipfile.ZipFile(p) as z:  # bound the uncompressed size before numpy inflates it
                total = sum(i.file_size for i in z.infolist())
            if total > MAX_CELLS + 1_000_000:
                raise FormatError(p, "file", f"at most {MAX_CELLS + 1_000_000} bytes uncompressed", total)
            with np.load(p, allow_pickle=False) as f:
                entries = set(f.files)
                want = {"format", "origin", "cell", "z_range", "known"}
                if entries != want:
                    raise FormatError(p, "entries", f"exactly {sorted(want)}", sorted(entries))
                fmt = str(f["format"])
                if fmt != FORMAT:
                    raise FormatError(p, "format", repr(FORMAT), repr(fmt[:40]))
                known = f["known"]
                if known.dtype != np.uint8 or known.ndim != 2 or not np.isin(known, (0, 1)).all():
                    raise FormatError(p, "known", "a 2-D uint8 grid of 0 and 1", f"{known.dtype} {known.shape}")
                cell = f["cell"]
                if cell.shape != () or not np.issubdtype(cell.dtype, np.floating):
                    raise FormatError(p, "cell", "a float scalar", f"{cell.dtype} {cell.shape}")
                origin, z_range = f["origin"], f["z_range"]
                try:
                    return cls(origin, float(cell), z_range, known.astype(bool))
                except ParameterError as e:
                    raise FormatError(p, "grid", "a valid known-space grid", str(e)) from None
        except FormatError:
            raise
        except (zipfile.BadZipFile, ValueError, OSError, KeyError) as e:
            raise FormatError(p, "file", "a .known.npz archive", f"{type(e).__name__}: {str(e)[:80]}") from None
