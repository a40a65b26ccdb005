"""Scan geometry and point clouds: each pixel's scan angles, and the maps as 3-D points in PLY or LAS.

**Frame** (right-handed, at the scanner, metres): ``z`` along the optical axis (the mirror's zero),
``x`` towards increasing column angle (right in the maps), ``y`` towards increasing row angle (down in
the maps, as image rows run), the camera frame of computer vision. A pixel with scan angles
``(ax, ay)`` (optical degrees; x from the columns, y from the rows) looks along the unit vector
``(tan ax, tan ay, 1) / |(tan ax, tan ay, 1)|``, and its point lies at the measured *range* (``depth_m``,
``c * tof / 2`` along the beam) on that ray, so ``|p| = depth_m`` exactly.

Files without scan geometry (the .mat files) take a field of view (``--fov-deg``) centred on the
axis; a pixel then spans ``fov / W`` by ``fov / H`` degrees.

One point per estimated pixel and surface, with ``intensity`` (detections attributed to the
return), ``uncertainty_m`` (1 sigma of the range), ``surface`` (0 nearest), ``return_number`` and
``number_of_returns`` (1..n per pixel, nearest first), and every flag the maps know:

- ``flags``: a bit set (:class:`PointFlag`; LAS: ``user_data``): 1 weak (background alone could
  have made this surface), 2 no return (the pixel's detections hold none; such points are written
  only when asked for, at the scanner's origin), 4 interpolated (spatial: the depth is the
  neighbours'), 8 not converged, 16 short (the acquisition's dwell, pass or time limit ended the
  pixel before its target), 32 incomplete (the session or stream ended before the pixel did);
- ``pixel_flag``: the pixel's ``recon.maps.PixelFlag``, ``acq_flag``: its ``acq.flags.AcqFlag``
  (0 for a file, which has none).

LAS also marks no-return points ``withheld`` (PDAL and CloudCompare leave withheld points out).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from enum import IntFlag
from pathlib import Path

import numpy as np

from spdepth.acq.flags import AcqFlag
from spdepth.recon.maps import C_M_PER_S, PixelFlag

POINT_FIELDS = ("x", "y", "z", "intensity", "uncertainty_m", "surface", "return_number", "number_of_returns",
                "flags", "pixel_flag", "acq_flag", "row", "col")
"""The columns of a point cloud (:func:`points_from_maps`), in PLY order."""


class PointFlag(IntFlag):
    """The ``flags`` bits of a point (PLY ``flags``, LAS ``user_data``)."""

    WEAK = 1
    """Background alone could have made this surface (``DepthMaps.weak``)."""
    NO_RETURN = 2
    """The pixel holds no return (``PixelFlag.NO_RETURN``); the point sits at the origin."""
    INTERPOLATED = 4
    """spatial: the depth comes from the neighbours (``PixelFlag.INTERPOLATED``)."""
    NOT_CONVERGED = 8
    """uos stopped at its iteration cap (``PixelFlag.NOT_CONVERGED``)."""
    SHORT = 16
    """The dwell, pass or time limit ended the pixel before its target (``AcqFlag`` 1-3)."""
    INCOMPLETE = 32
    """The session or the replayed stream ended before the pixel was complete (``AcqFlag.INCOMPLETE``)."""


@dataclass(frozen=True)
class ScanGeometry:
    """Scan angles of an H x W scan: pixel centres of the first and last column (x) and row (y),
    optical degrees (``acq.plan.ScanPlan``'s convention)."""

    shape: tuple[int, int]
    x_first_deg: float
    x_last_deg: float
    y_first_deg: float
    y_last_deg: float

    @classmethod
    def from_plan(cls, plan) -> "ScanGeometry | None":
        """The angles of an ``acq.plan.ScanPlan``; None for a plan without angles (a foreign
        recording replayed gets a plan with every angle 0 along an axis of several pixels): no
        geometry rather than a false one."""
        if (plan.nx > 1 and plan.x_first_deg == plan.x_last_deg) or \
                (plan.ny > 1 and plan.y_first_deg == plan.y_last_deg):
            return None
        return cls(tuple(plan.shape), plan.x_first_deg, plan.x_last_deg, plan.y_first_deg,
                   plan.y_last_deg)

    @classmethod
    def from_fov(cls, shape: tuple[int, int], fov_deg: float | tuple[float, float]) -> "ScanGeometry":
        """A field ``fov_deg`` wide (one number: square; or (x, y)) centred on the axis, pixel centres
        half a pixel inside its edges."""
        h, w = (int(v) for v in shape)
        fx, fy = (fov_deg, fov_deg) if np.isscalar(fov_deg) else fov_deg
        x = [-fx / 2 + (c + 0.5) * fx / w for c in (0, w - 1)]
        y = [-fy / 2 + (r + 0.5) * fy / h for r in (0, h - 1)]
        return cls((h, w), x[0], x[1], y[0], y[1])

    @property
    def col_deg(self) -> np.ndarray:
        """(W,) scan angle of each column's centre."""
        return np.linspace(self.x_first_deg, self.x_last_deg, self.shape[1])

    @property
    def row_deg(self) -> np.ndarray:
        """(H,) scan angle of each row's centre."""
        return np.linspace(self.y_first_deg, self.y_last_deg, self.shape[0])

    @property
    def pixel_deg(self) -> tuple[float, float]:
        """(width, height) of one pixel in degrees (a one-pixel axis: 1 degree, nothing to measure)."""
        h, w = self.shape
        dx = abs(self.x_last_deg - self.x_first_deg) / (w - 1) if w > 1 else 0.0
        dy = abs(self.y_last_deg - self.y_first_deg) / (h - 1) if h > 1 else 0.0
        dx, dy = dx or dy or 1.0, dy or dx or 1.0
        return dx, dy

    @property
    def extent_deg(self) -> tuple[float, float, float, float]:
        """(left, right, top, bottom): the angles of the outer pixel edges, column 0 left, row 0 top."""
        dx, dy = self.pixel_deg
        sx = 1.0 if self.x_last_deg >= self.x_first_deg else -1.0
        sy = 1.0 if self.y_last_deg >= self.y_first_deg else -1.0
        return (self.x_first_deg - sx * dx / 2, self.x_last_deg + sx * dx / 2,
                self.y_first_deg - sy * dy / 2, self.y_last_deg + sy * dy / 2)

    @property
    def fov_deg(self) -> tuple[float, float]:
        """(x, y) field of view from the outer pixel edges."""
        left, right, top, bottom = self.extent_deg
        return abs(right - left), abs(bottom - top)

    def directions(self) -> np.ndarray:
        """(H, W, 3) unit vectors of the pixels' rays in the scanner frame (module docstring)."""
        tx = np.tan(np.radians(self.col_deg))[None, :]
        ty = np.tan(np.radians(self.row_deg))[:, None]
        tx, ty = np.broadcast_arrays(tx, ty)
        d = np.stack([tx, ty, np.ones_like(tx)], axis=-1)
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    def directions_at(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """(N, 3) the rays of the pixels (rows[i], cols[i]), as :meth:`directions` gives them
        (the same floats), without the whole frame's (H, W, 3)."""
        tx = np.tan(np.radians(self.col_deg))[cols]
        ty = np.tan(np.radians(self.row_deg))[rows]
        d = np.stack([tx, ty, np.ones_like(tx)], axis=-1)
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    def to_dict(self) -> dict:
        # "rows"/"cols", not "shape": tifffile takes a JSON description holding "shape" for its own
        d = asdict(self)
        del d["shape"]
        return {"rows": self.shape[0], "cols": self.shape[1], **d}

    @classmethod
    def from_dict(cls, d: dict) -> "ScanGeometry":
        return cls((int(d["rows"]), int(d["cols"])), float(d["x_first_deg"]),
                   float(d["x_last_deg"]), float(d["y_first_deg"]), float(d["y_last_deg"]))


GEOMETRY_KEY = "geometry"
"""Where a maps object's ``settings`` hold its :class:`ScanGeometry` (``to_dict``)."""


def geometry_of(maps) -> ScanGeometry | None:
    """The scan geometry a maps object carries in its settings (None: none, e.g. a .mat file read
    without ``--fov-deg``)."""
    d = (getattr(maps, "settings", None) or {}).get(GEOMETRY_KEY)
    return ScanGeometry.from_dict(d) if d else None


def _surfaces(a) -> np.ndarray:
    a = np.asarray(a)
    return a if a.ndim == 3 else a[None]


@dataclass(frozen=True)
class PointCloud:
    """Columns of :data:`POINT_FIELDS`, each (N,): x, y, z (m), intensity (detections),
    uncertainty_m, surface (0 nearest), return_number / number_of_returns (1..n per pixel, by
    range), flags (:class:`PointFlag` bits), pixel_flag (``PixelFlag``), acq_flag (``AcqFlag``),
    row, col (the pixel)."""

    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    intensity: np.ndarray
    uncertainty_m: np.ndarray
    surface: np.ndarray
    return_number: np.ndarray
    number_of_returns: np.ndarray
    flags: np.ndarray
    pixel_flag: np.ndarray
    acq_flag: np.ndarray
    row: np.ndarray
    col: np.ndarray

    def __len__(self) -> int:
        return int(self.x.size)

    @property
    def xyz(self) -> np.ndarray:
        return np.stack([self.x, self.y, self.z], axis=1)

    @property
    def range_m(self) -> np.ndarray:
        return np.sqrt(self.x ** 2 + self.y ** 2 + self.z ** 2)


def points_from_maps(maps, geometry: ScanGeometry, *, depth_m=None, no_return: bool = False,
                     acq_flags=None) -> PointCloud:
    """One point per pixel and surface with a finite depth, and with ``no_return`` one at the origin
    per pixel that has detections but no return (flag NO_RETURN). ``maps``: a ``DepthMaps`` or a
    session's maps (anything with ``depth_m``, ``signal``, ``uncertainty_s``, ``flags``, optionally
    ``weak`` and ``acq_flags``; (H, W) or (K, H, W)); ``depth_m`` replaces ``maps.depth_m`` (e.g. a
    live snapshot's); ``acq_flags`` (H, W) a session's ``AcqFlag`` map (else ``maps.acq_flags``)."""
    depth = _surfaces(maps.depth_m if depth_m is None else depth_m)
    k, h, w = depth.shape
    if (h, w) != tuple(geometry.shape):
        raise ValueError(f"maps of {w}x{h} pixels do not match a {geometry.shape[1]}x"
                         f"{geometry.shape[0]} scan geometry")
    # the stand-ins of maps a maps object lacks are made only then (a getattr default is built
    # on every call: a 4096 x 4096 NaN map each time)
    signal = _surfaces(maps.signal if hasattr(maps, "signal") else np.zeros((h, w)))
    sd_s = _surfaces(maps.uncertainty_s if hasattr(maps, "uncertainty_s") else np.full((h, w), np.nan))
    flags = np.asarray(maps.flags if hasattr(maps, "flags") else np.zeros((h, w), np.uint8))
    weak = getattr(maps, "weak", None)
    if weak is not None and _surfaces(weak).shape != depth.shape:
        weak = None
    acq = getattr(maps, "acq_flags", None) if acq_flags is None else acq_flags
    # everything per point is computed on the pixels with a surface only (a 4096 x 4096 scan cut
    # by its time limit has a few hundred thousand among 16 M): no full-frame temporaries but
    # the masks
    has = np.isfinite(depth).any(axis=0).reshape(-1)
    pix = np.flatnonzero(has)
    sub = depth.reshape(k, -1)[:, pix].astype(np.float64)          # (K, n)
    ok = np.isfinite(sub)
    # per pixel, the surfaces by range: return number 1 the nearest, of as many as the pixel holds
    order = np.argsort(np.where(ok, sub, np.inf), axis=0, kind="stable")
    rank = np.empty_like(order)
    np.put_along_axis(rank, order, np.arange(k)[:, None].repeat(pix.size, 1), axis=0)
    count = ok.sum(axis=0)
    surf, j = np.nonzero(ok)             # surface-major, then pixels in flat order
    flat = pix[j]
    rng = sub[ok]
    ret = rank[surf, j] + 1
    nret = count[j]
    if no_return:
        nr = np.flatnonzero((flags.reshape(-1) == PixelFlag.NO_RETURN) & ~has)
        surf = np.concatenate([surf, np.zeros(nr.size, surf.dtype)])
        flat = np.concatenate([flat, nr])
        rng = np.concatenate([rng, np.zeros(nr.size)])
        ret = np.concatenate([ret, np.ones(nr.size, ret.dtype)])
        nret = np.concatenate([nret, np.ones(nr.size, nret.dtype)])
    rr, cc = np.divmod(flat, w)
    d = geometry.directions_at(rr, cc)
    p = d * rng[:, None]

    def pick(a):
        a = np.asarray(a)
        return a[surf if a.shape[0] == k else 0, rr, cc]

    pf = flags[rr, cc].astype(np.uint8)
    af = np.zeros(rr.size, np.uint8) if acq is None else np.asarray(acq)[rr, cc].astype(np.uint8)
    bits = np.zeros(rr.size, np.uint8)
    if weak is not None:
        bits |= np.where(pick(_surfaces(weak)).astype(bool), PointFlag.WEAK, 0).astype(np.uint8)
    bits |= np.where(pf == PixelFlag.NO_RETURN, PointFlag.NO_RETURN, 0).astype(np.uint8)
    bits |= np.where(pf == PixelFlag.INTERPOLATED, PointFlag.INTERPOLATED, 0).astype(np.uint8)
    bits |= np.where(pf == PixelFlag.NOT_CONVERGED, PointFlag.NOT_CONVERGED, 0).astype(np.uint8)
    short = np.isin(af, [AcqFlag.DWELL_LIMIT, AcqFlag.PASS_LIMIT, AcqFlag.TIME_LIMIT])
    bits |= np.where(short, PointFlag.SHORT, 0).astype(np.uint8)
    bits |= np.where(af == AcqFlag.INCOMPLETE, PointFlag.INCOMPLETE, 0).astype(np.uint8)
    unc = np.where(pf == PixelFlag.NO_RETURN, np.nan, pick(sd_s) * C_M_PER_S / 2)
    return PointCloud(
        x=p[:, 0], y=p[:, 1], z=p[:, 2],
        intensity=np.where(pf == PixelFlag.NO_RETURN, 0.0, pick(signal)).astype(np.float32),
        uncertainty_m=unc.astype(np.float32), surface=surf.astype(np.uint8),
        return_number=ret.astype(np.uint8), number_of_returns=nret.astype(np.uint8),
        flags=bits, pixel_flag=pf, acq_flag=af.astype(np.uint8),
        row=rr.astype(np.int32), col=cc.astype(np.int32))


def write_ply(path: str | Path, cloud: PointCloud, *, comments: tuple[str, ...] = ()) -> Path:
    """Binary little-endian PLY (plyfile): vertex x, y, z (float64, m), intensity, uncertainty_m
    (float32), surface, return_number, number_of_returns, flags (:class:`PointFlag` bits),
    pixel_flag, acq_flag (uint8), row, col (int32); a comment says what the flag bits mean."""
    from plyfile import PlyData, PlyElement

    path = Path(path)
    dtype = [("x", "f8"), ("y", "f8"), ("z", "f8"), ("intensity", "f4"), ("uncertainty_m", "f4"),
             ("surface", "u1"), ("return_number", "u1"), ("number_of_returns", "u1"), ("flags", "u1"),
             ("pixel_flag", "u1"), ("acq_flag", "u1"), ("row", "i4"), ("col", "i4")]
    v = np.empty(len(cloud), dtype=dtype)
    for name, _ in dtype:
        v[name] = getattr(cloud, name)
    frame = ("frame: right-handed at the scanner, metres; z along the optical axis, x towards "
             "increasing column angle, y towards increasing row angle")
    PlyData([PlyElement.describe(v, "vertex")], text=False,
            comments=[frame, FLAGS_NOTE, *comments]).write(str(path))
    return path


FLAGS_NOTE = ("flags bits: " + ", ".join(f"{int(f)} {f.name.lower().replace('_', ' ')}" for f in PointFlag)
              + "; pixel_flag: recon PixelFlag, acq_flag: AcqFlag")


def write_las(path: str | Path, cloud: PointCloud, *, description: str = "") -> Path:
    """LAS 1.4, point format 6 (laspy): x, y, z at 0.1 mm, ``intensity`` (detections scaled to
    uint16, x100), ``return_number`` / ``number_of_returns`` (1..n per pixel, nearest first),
    ``user_data`` the :class:`PointFlag` bits, ``withheld`` set on no-return points,
    ``point_source_id`` the surface index, and extra dimensions ``uncertainty_m`` (float32),
    ``surface``, ``pixel_flag``, ``acq_flag`` (uint8), ``row``, ``col`` (int32)."""
    import laspy

    path = Path(path)
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales = np.array([1e-4, 1e-4, 1e-4])
    xyz = cloud.xyz
    header.offsets = np.floor(xyz.min(axis=0)) if len(cloud) else np.zeros(3)
    header.add_extra_dims([laspy.ExtraBytesParams(name="uncertainty_m", type=np.float32),
                           laspy.ExtraBytesParams(name="surface", type=np.uint8),
                           laspy.ExtraBytesParams(name="pixel_flag", type=np.uint8),
                           laspy.ExtraBytesParams(name="acq_flag", type=np.uint8),
                           laspy.ExtraBytesParams(name="row", type=np.int32),
                           laspy.ExtraBytesParams(name="col", type=np.int32)])
    if description:
        header.generating_software = "spdepth"[:32]
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    las.intensity = np.clip(np.round(cloud.intensity * 100), 0, 65535).astype(np.uint16)
    las.return_number = cloud.return_number
    las.number_of_returns = cloud.number_of_returns
    las.user_data = cloud.flags
    las.withheld = (cloud.flags & PointFlag.NO_RETURN) != 0
    las.point_source_id = cloud.surface.astype(np.uint16)
    las.uncertainty_m = cloud.uncertainty_m
    las.surface = cloud.surface
    las.pixel_flag = cloud.pixel_flag
    las.acq_flag = cloud.acq_flag
    las.row = cloud.row
    las.col = cloud.col
    las.write(str(path))
    return path


def write_points(maps, geometry: ScanGeometry, *, ply: str | Path | None = None,
                 las: str | Path | None = None, note: str = "", no_return: bool = False,
                 acq_flags=None) -> int:
    """Write the maps' points to ``ply`` and/or ``las`` (with ``no_return``, also the pixels without
    a return, flagged, at the origin); returns how many points."""
    cloud = points_from_maps(maps, geometry, no_return=no_return, acq_flags=acq_flags)
    comments = (f"geometry: {json.dumps(geometry.to_dict())}",) + ((note,) if note else ())
    if ply:
        write_ply(ply, cloud, comments=comments)
    if las:
        write_las(las, cloud, description=note)
    return len(cloud)


def range_offset_m(range_offset: float | None = None, gate_delay_s: float | None = None) -> float:
    """The range to add to ``c * tof / 2`` for gated data: ``range_offset`` as given, or the gate
    delay's ``c * delay / 2``; 0 without either."""
    if range_offset is not None:
        return float(range_offset)
    if gate_delay_s is not None:
        return float(gate_delay_s) * C_M_PER_S / 2
    return 0.0


__all__ = ["ScanGeometry", "PointCloud", "PointFlag", "POINT_FIELDS", "GEOMETRY_KEY", "geometry_of",
           "points_from_maps", "write_ply", "write_las", "write_points", "range_offset_m"]
