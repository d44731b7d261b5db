"""``PanelSet``: the typed hand-off of the 3D glass panels, written by ``regularize_corners`` into
``04_regularize/panels.json`` and read by ``correct_mesh`` and ``bake_normals``.

All geometry is in the local frame of ``01_import`` (z up, metres). Each facade part has a surface model
(``PartSurface``): a plane, or a cylinder with a vertical axis whose rulings are the panel columns. Surface
coordinates of a part (metres): ``s`` along the surface, left to right as seen from outside (arc length on
a cylinder), ``z`` up (world z), ``h`` along the outward normal (0 on the glass).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from facade_pipeline.errors import InputError
from facade_pipeline.io.atomic import read_json, write_json

PANELSET_VERSION = 1
UP = np.array([0.0, 0.0, 1.0])
SurfaceKind = Literal["planar", "cylindrical"]


@dataclass(frozen=True, eq=False)
class PartSurface:
    """The glass surface of one facade part, in the local frame (m).

    planar: the plane through ``origin`` [3] with unit outward ``normal`` [3] (horizontal).
    cylindrical: the vertical cylinder of ``radius_m`` around the axis through ``origin`` [3] (its z is
    ignored); ``convex`` means the outward normal points away from the axis. ``ref_angle_rad`` is the
    azimuth where s = 0.
    """

    kind: SurfaceKind
    origin: np.ndarray
    normal: np.ndarray
    radius_m: float = 0.0
    convex: bool = True
    ref_angle_rad: float = 0.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "origin", np.asarray(self.origin, dtype=np.float64).reshape(3))
        object.__setattr__(self, "normal", np.asarray(self.normal, dtype=np.float64).reshape(3))

    @property
    def sign(self) -> float:
        """+1 when the outward normal points away from the cylinder axis, -1 toward it."""
        return 1.0 if self.convex else -1.0

    def coords(self, points: np.ndarray) -> np.ndarray:
        """World points [N, 3] -> surface coordinates (s, z, h) [N, 3] (m)."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if self.kind == "planar":
            right = np.cross(UP, self.normal)
            q = p - self.origin
            return np.stack([q @ right, p[:, 2], q @ self.normal], axis=1)
        dx, dy = p[:, 0] - self.origin[0], p[:, 1] - self.origin[1]
        ang = np.angle(np.exp(1j * (np.arctan2(dy, dx) - self.ref_angle_rad)))
        r = np.hypot(dx, dy)
        return np.stack([self.sign * self.radius_m * ang, p[:, 2], self.sign * (r - self.radius_m)], axis=1)

    def points(self, szh: np.ndarray) -> np.ndarray:
        """Surface coordinates (s, z, h) [N, 3] -> world points [N, 3] (inverse of ``coords``)."""
        c = np.asarray(szh, dtype=np.float64).reshape(-1, 3)
        if self.kind == "planar":
            right = np.cross(UP, self.normal)
            out = self.origin + c[:, :1] * right + c[:, 2:3] * self.normal
            out[:, 2] = c[:, 1]
            return out
        ang = self.ref_angle_rad + self.sign * c[:, 0] / self.radius_m
        r = self.radius_m + self.sign * c[:, 2]
        return np.stack([self.origin[0] + r * np.cos(ang), self.origin[1] + r * np.sin(ang), c[:, 1]], axis=1)

    def normals_at(self, points: np.ndarray) -> np.ndarray:
        """Unit outward normals [N, 3] of the surface at the feet of world points [N, 3]."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if self.kind == "planar":
            return np.broadcast_to(self.normal, p.shape).copy()
        d = p[:, :2] - self.origin[:2]
        d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
        return self.sign * np.concatenate([d, np.zeros((len(p), 1))], axis=1)

    def shifted(self, delta_m: float) -> PartSurface:
        """The surface moved by ``delta_m`` along its outward normal (h = delta_m becomes h = 0)."""
        if self.kind == "planar":
            return PartSurface("planar", self.origin + delta_m * self.normal, self.normal)
        return PartSurface(
            "cylindrical",
            self.origin,
            self.normal,
            self.radius_m + self.sign * delta_m,
            self.convex,
            self.ref_angle_rad,
        )

    def intersect(self, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """Distance t [N] along unit rays (origins, dirs [N, 3]) to the surface, the nearest positive one
        whose surface faces the ray's origin; inf where there is none (parallel rays, misses)."""
        o, d = np.asarray(origins, np.float64).reshape(-1, 3), np.asarray(dirs, np.float64).reshape(-1, 3)
        if self.kind == "planar":
            den = d @ self.normal
            with np.errstate(divide="ignore", invalid="ignore"):
                t = ((self.origin - o) @ self.normal) / den
            return np.where((np.abs(den) > 1e-9) & (t > 0), t, np.inf)
        oc = o[:, :2] - self.origin[:2]
        a = (d[:, :2] ** 2).sum(1)
        b = 2 * (oc * d[:, :2]).sum(1)
        c = (oc**2).sum(1) - self.radius_m**2
        disc = b * b - 4 * a * c
        ok = (a > 1e-12) & (disc >= 0)
        sq = np.sqrt(np.where(ok, disc, 0.0))
        with np.errstate(divide="ignore", invalid="ignore"):
            roots = np.stack([(-b - sq) / (2 * a), (-b + sq) / (2 * a)], axis=1)  # [N, 2]
        hit = o[:, None, :] + roots[..., None] * d[:, None, :]
        n = self.sign * (hit[..., :2] - self.origin[:2])
        facing = (n * d[:, None, :2]).sum(-1) < 0
        good = ok[:, None] & (roots > 0) & facing
        return np.where(good, roots, np.inf).min(axis=1)

    def to_dict(self) -> dict:
        return {
            "kind": self.kind,
            "origin": self.origin.tolist(),
            "normal": self.normal.tolist(),
            "radius_m": self.radius_m,
            "convex": self.convex,
            "ref_angle_rad": self.ref_angle_rad,
        }

    @classmethod
    def from_dict(cls, d: dict) -> PartSurface:
        return cls(
            d["kind"],
            d["origin"],
            d["normal"],
            float(d["radius_m"]),
            bool(d["convex"]),
            float(d["ref_angle_rad"]),
        )


@dataclass(frozen=True, eq=False)
class Panel:
    """One 3D glass panel: ``corners`` [4, 3] (bottom-left, bottom-right, top-right, top-left seen from
    outside, local frame, m), the plane through them (unit outward ``normal`` [3] and ``offset_m`` with
    normal . x = offset_m), and its ``row`` (bottom to top) and ``col`` (left to right) in its ``part``."""

    part: int
    row: int
    col: int
    corners: np.ndarray
    normal: np.ndarray
    offset_m: float
    n_views: int = 1

    def __post_init__(self) -> None:
        object.__setattr__(self, "corners", np.asarray(self.corners, dtype=np.float64).reshape(4, 3))
        object.__setattr__(self, "normal", np.asarray(self.normal, dtype=np.float64).reshape(3))

    @property
    def center(self) -> np.ndarray:  # [3]
        return self.corners.mean(axis=0)

    @property
    def width_m(self) -> float:
        """Mean length of the bottom and top edges (m)."""
        c = self.corners
        return float(0.5 * (np.linalg.norm(c[1] - c[0]) + np.linalg.norm(c[2] - c[3])))

    def to_dict(self) -> dict:
        return {
            "part": self.part,
            "row": self.row,
            "col": self.col,
            "corners": self.corners.tolist(),
            "normal": self.normal.tolist(),
            "offset_m": self.offset_m,
            "n_views": self.n_views,
        }

    @classmethod
    def from_dict(cls, d: dict) -> Panel:
        return cls(
            int(d["part"]),
            int(d["row"]),
            int(d["col"]),
            d["corners"],
            d["normal"],
            float(d["offset_m"]),
            int(d["n_views"]),
        )


@dataclass(frozen=True, eq=False)
class PanelSet:
    """The 3D panels of a building and the surface of each facade part (index = part number)."""

    parts: tuple[PartSurface, ...]
    panels: tuple[Panel, ...]
    meta: dict = field(default_factory=dict)

    def of_part(self, part: int) -> tuple[Panel, ...]:
        return tuple(p for p in self.panels if p.part == part)

    def save(self, path: str | Path) -> None:
        write_json(
            path,
            {
                "version": PANELSET_VERSION,
                "frame": "local (01_import), metres, z up",
                "corner_order": "bottom-left, bottom-right, top-right, top-left as seen from outside",
                "parts": [p.to_dict() for p in self.parts],
                "panels": [p.to_dict() for p in self.panels],
                "meta": self.meta,
            },
        )

    @classmethod
    def load(cls, path: str | Path) -> PanelSet:
        """Read and check a panel set; a damaged file raises ``InputError`` naming it."""
        def parse(d: dict) -> tuple:
            parts = tuple(PartSurface.from_dict(p) for p in d["parts"])
            return parts, tuple(Panel.from_dict(p) for p in d["panels"]), d.get("meta", {})

        what = "a panel set (JSON with parts and panels) written by regularize_corners"
        parts, panels, meta = read_json(path, what, parse, PANELSET_VERSION)
        bad = [
            i
            for i, p in enumerate(panels)
            if not (0 <= p.part < len(parts)) or not np.isfinite(p.corners).all()
        ]
        if bad:
            raise InputError(
                path,
                f"panels with finite corners and a part index below {len(parts)}",
                f"{len(bad)} bad panels (first: #{bad[0]})",
            )
        return cls(parts, panels, meta)


def frame_width(panels: tuple[Panel, ...], surface: PartSurface) -> float:
    """A part's frame width (m): the median gap between neighbouring panels (zero with a single panel)."""
    szh = np.stack([surface.coords(p.corners) for p in panels])  # [P, 4, 3]
    gaps = []
    for axis, (lo_k, hi_k) in ((0, (1, 0)), (1, (2, 1))):  # s: right -> next left; z: top -> next bottom
        lo = np.unique(np.round(szh[:, hi_k, axis], 6))
        hi = np.unique(np.round(szh[:, lo_k, axis], 6))
        d = lo[:, None] - hi[None]
        d = d[d > 0]
        if len(d):
            gaps.append(float(d.min()))
    return float(np.median(gaps)) if gaps else 0.0


def part_outline(panels: tuple[Panel, ...], surface: PartSurface) -> np.ndarray:
    """Surface coordinates [4, 3] of a part's facade: its panels' extent grown by one frame width
    (``frame_width``)."""
    szh = np.stack([surface.coords(p.corners) for p in panels])  # [P, 4, 3]
    fw = frame_width(panels, surface)
    s0, s1 = szh[..., 0].min() - fw, szh[..., 0].max() + fw
    z0, z1 = szh[..., 1].min() - fw, szh[..., 1].max() + fw
    return np.array([[s0, z0, 0.0], [s1, z0, 0.0], [s1, z1, 0.0], [s0, z1, 0.0]])
