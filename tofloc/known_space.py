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
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from tofloc.atomic import atomic_path
from tofloc.errors import FormatError, ParameterError
from tofloc.npy_input import check_npz_member_headers

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

    def _boundary_scene(self) -> Any:
        """An Open3D ray-casting scene of the known space's boundary (cached): a vertical
        quad on every edge between a known and an unknown cell (the grid's outside counts
        as unknown), from ``z_range[0]`` to ``z_range[1]``, and the two horizontal planes at
        those heights over the grid."""
        scene = self.__dict__.get("_scene")
        if scene is None:
            import open3d as o3d

            k = np.pad(self.known, 1, constant_values=False)
            (x0, y0), c = self.origin - self.cell, self.cell  # corner of the padded grid
            zlo, zhi = (float(v) for v in self.z_range)
            quads = []
            # edges between cells (i, j) and (i + 1, j): the plane x = x0 + (i + 1) c
            i, j = np.nonzero(k[:-1, :] != k[1:, :])
            x = x0 + (i + 1) * c
            quads.append(np.stack([np.column_stack([x, y0 + j * c]), np.column_stack([x, y0 + (j + 1) * c])], axis=1))
            i, j = np.nonzero(k[:, :-1] != k[:, 1:])
            y = y0 + (j + 1) * c
            quads.append(np.stack([np.column_stack([x0 + i * c, y]), np.column_stack([x0 + (i + 1) * c, y])], axis=1))
            seg = np.concatenate(quads)  # (n, 2 ends, xy)
            n = len(seg)
            v = np.empty((n, 4, 3))
            v[:, 0, :2], v[:, 1, :2], v[:, 2, :2], v[:, 3, :2] = seg[:, 0], seg[:, 1], seg[:, 1], seg[:, 0]
            v[:, :2, 2], v[:, 2:, 2] = zlo, zhi
            nx, ny = k.shape
            x1, y1 = x0 + nx * c, y0 + ny * c
            caps = np.array([[[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]] for z in (zlo, zhi)])
            v = np.concatenate([v, caps]).reshape(-1, 3).astype(np.float32)
            base = np.arange(n + 2, dtype=np.uint32)[:, None] * 4
            tris = np.concatenate([base + [0, 1, 2], base + [0, 2, 3]]).astype(np.uint32)
            scene = o3d.t.geometry.RaycastingScene()
            scene.add_triangles(o3d.core.Tensor(v), o3d.core.Tensor(tris))
            self.__dict__["_scene"] = scene
        return scene

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state.pop("_scene", None)  # rebuilt on first use (cheap)
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)

    def unknown_entry_reading(self, origins: ArrayLike, directions: ArrayLike, reach: ArrayLike,
                              along: ArrayLike) -> NDArray[np.float64]:
        """:meth:`unknown_entry` of zones' rays in readings: ``reach`` and the result are
        readings (``inf``: known space up to ``reach``), ``along`` the reading per metre of
        ray (a zone table's :attr:`tofloc.zone_caster.ZoneCaster.along`). What the beam
        model and the fit check ask of a map built from scans."""
        along = np.asarray(along, dtype=float)
        return self.unknown_entry(origins, directions, np.asarray(reach, dtype=float) / along) * along

    def unknown_entry(self, origins: ArrayLike, directions: ArrayLike, max_t: ArrayLike) -> NDArray[np.float64]:
        """Distance along each ray to where it first enters unknown space (``inf`` when it
        stays in known space up to ``max_t``; 0 when it starts there).

        One Embree ray cast against the known space's boundary (:meth:`_boundary_scene`):
        the first crossing of a known/unknown cell edge or of a height limit. A plain march
        in half-cell steps gives the same distance to within half a cell (tested), at
        hundreds of lookups per ray instead of one cast.

        Parameters
        ----------
        origins : array (..., 3)
        directions : array (..., 3)
            Unit directions (broadcast against ``origins``).
        max_t : array (...)
            How far to look along each ray (m).
        """
        import open3d as o3d

        from tofloc.threads import open3d_threads

        o = np.asarray(origins, dtype=float)
        d = np.asarray(directions, dtype=float)
        tmax = np.asarray(max_t, dtype=float)
        shape = np.broadcast_shapes(o.shape[:-1], d.shape[:-1], tmax.shape)
        rays = np.empty(shape + (6,), dtype=np.float32)
        rays[..., :3] = o
        rays[..., 3:] = d
        rays = rays.reshape(-1, 6)
        tm = np.broadcast_to(tmax, shape).reshape(-1)
        ans = self._boundary_scene().cast_rays(o3d.core.Tensor.from_numpy(rays), nthreads=open3d_threads())
        t = ans["t_hit"].numpy().astype(np.float64)
        t[~self.is_known(rays[:, :3].astype(np.float64))] = 0.0
        t[~((t <= tm) & (tm > 0))] = np.inf
        return t.reshape(shape)

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
                infos = z.infolist()
            total = sum(i.file_size for i in infos)
            if total > MAX_CELLS + 1_000_000:
                raise FormatError(p, "file", f"at most {MAX_CELLS + 1_000_000} bytes uncompressed", total)
            wanted = {f"{n}.npy": n for n in ("format", "origin", "cell", "z_range", "known")}
            check_npz_member_headers(infos, p, wanted, lambda field, expected, found: FormatError(p, field, expected, found))
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
                for name, a in (("origin", origin), ("z_range", z_range)):
                    if a.shape != (2,) or not np.issubdtype(a.dtype, np.floating):  # complex lost its imaginary part
                        raise FormatError(p, name, "2 float numbers", f"{a.dtype} {a.shape}")
                try:
                    return cls(origin, float(cell), z_range, known.astype(bool))
                except ParameterError as e:
                    raise FormatError(p, "grid", "a valid known-space grid", str(e)) from None
        except FormatError:
            raise
        except (zipfile.BadZipFile, ValueError, OSError, KeyError) as e:
            raise FormatError(p, "file", "a .known.npz archive", f"{type(e).__name__}: {str(e)[:80]}") from None
