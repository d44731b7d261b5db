"""Facade parts: the surface map of a planar or cylindrical part, its panel grid, and its true meshes.

Surface coordinates of a part (all in metres): ``s`` along the glass surface, left to right as seen from
outside (s = 0 at the facade frame origin; the arc length on a cylinder), ``z`` up from the origin, ``h``
along the outward normal (h = 0 on the glass). In the facade frame (x = y cross z, y out, z up):

- planar: (x, y, z) = (-s, h, z);
- cylindrical, radius R, axis at (0, -R): phi = s / R, (x, y) = (-(R + h) sin phi, (R + h) cos phi - R).

Mullions and transoms are bars of width ``frame_width_m`` centred on the grid lines, spanning h in
[-frame_back_m, frame_depth_m]; the outermost bars lie inside the part's width and height. A panel's glass
is the opening between bars at h = 0; its corners are the opening's corners.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from facade_pipeline.synthetic.mesh import Material, TriMesh, concat, prism, quads_to_mesh, sheet
from facade_pipeline.synthetic.params import SHELVES_MAX, FacadePart, FacadeStyle


@dataclass(frozen=True, eq=False)
class PartGeometry:
    """The geometry of one facade part. ``world_from_facade`` [4, 4] is a rigid transform."""

    index: int
    part: FacadePart
    world_from_facade: np.ndarray
    frame_width_m: float

    @property
    def radius(self) -> float:
        return self.part.radius_m if self.part.kind == "cylindrical" else math.inf

    @property
    def s_lines(self) -> np.ndarray:  # [cols + 1] s of the mullion centre lines
        p, fw = self.part, self.frame_width_m
        return -p.width_m / 2 + fw / 2 + np.arange(p.cols + 1) * (p.width_m - fw) / p.cols

    @property
    def z_lines(self) -> np.ndarray:  # [rows + 1] z of the transom centre lines
        p, fw = self.part, self.frame_width_m
        return fw / 2 + np.arange(p.rows + 1) * (p.height_m - fw) / p.rows

    def facade_point(self, s: np.ndarray, z: np.ndarray, h: np.ndarray) -> np.ndarray:
        """Surface coordinates -> facade-frame points [..., 3] (see the module docstring)."""
        s, z, h = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in (s, z, h)))
        if self.part.kind == "planar":
            return np.stack([-s, h, z], axis=-1)
        R = self.part.radius_m
        phi = s / R
        return np.stack([-(R + h) * np.sin(phi), (R + h) * np.cos(phi) - R, z], axis=-1)

    def surface(self, s: np.ndarray, z: np.ndarray, h: np.ndarray) -> np.ndarray:
        """Surface coordinates -> world points [..., 3] (m)."""
        T = self.world_from_facade
        return self.facade_point(s, z, h) @ T[:3, :3].T + T[:3, 3]

    def normal(self, s: np.ndarray) -> np.ndarray:
        """World outward unit normal [..., 3] of the glass surface at ``s``."""
        s = np.asarray(s, dtype=np.float64)
        phi = np.zeros_like(s) if self.part.kind == "planar" else s / self.part.radius_m
        n = np.stack([-np.sin(phi), np.cos(phi), np.zeros_like(phi)], axis=-1)
        return n @ self.world_from_facade[:3, :3].T

    def tangent(self, s: np.ndarray) -> np.ndarray:
        """World unit vector [..., 3] of increasing ``s`` (to the right of a viewer outside)."""
        return np.cross(np.array([0.0, 0.0, 1.0]), self.normal(s))

    def surface_coords(self, world: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Inverse of ``surface``: world points [N, 3] -> (s, z, h) [N] each."""
        T = self.world_from_facade
        f = (np.asarray(world, dtype=np.float64) - T[:3, 3]) @ T[:3, :3]
        if self.part.kind == "planar":
            return -f[:, 0], f[:, 2], f[:, 1]
        R = self.part.radius_m
        phi = np.arctan2(-f[:, 0], f[:, 1] + R)
        return R * phi, f[:, 2], np.hypot(f[:, 0], f[:, 1] + R) - R

    def panel_bounds(self, row: int, col: int) -> tuple[float, float, float, float]:
        """(s0, s1, z0, z1) of the glass opening of panel (row, col)."""
        s, z, hw = self.s_lines, self.z_lines, self.frame_width_m / 2
        return s[col] + hw, s[col + 1] - hw, z[row] + hw, z[row + 1] - hw


def world_from_facade(part: FacadePart) -> np.ndarray:
    """[4, 4] rigid transform of ``part``: y = outward normal at azimuth ``facing_deg``, z up, x = y x z."""
    f = math.radians(part.facing_deg)
    y = np.array([math.cos(f), math.sin(f), 0.0])
    z = np.array([0.0, 0.0, 1.0])
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2] = np.cross(y, z), y, z
    T[:3, 3] = part.origin_m
    return T


@dataclass(frozen=True, eq=False)
class Panel:
    """One glass panel: corners [4, 3] (bottom-left, bottom-right, top-right, top-left seen from outside,
    world m, on the glass surface), outward unit normal [3] at its centre, and its diffuse colour D [3]."""

    part: int
    row: int
    col: int
    corners: np.ndarray
    normal: np.ndarray
    diffuse: np.ndarray
    glazed: bool = True
    """False for a unit without glass ("unglazed_units"): an opening onto a room, not a panel."""


def build_panels(
    geom: PartGeometry, style: FacadeStyle, rng: np.random.Generator, unglazed: frozenset = frozenset()
) -> list[Panel]:
    """The panels of one part, rows bottom to top then columns left to right. D = tint * interior * (1 + v u),
    u uniform in [-1, 1] per panel (v = ``interior_variation``); the (row, col) in ``unglazed`` have no
    glass."""
    base = np.asarray(style.glass_tint) * np.asarray(style.interior_color)
    out = []
    for r in range(geom.part.rows):
        for c in range(geom.part.cols):
            s0, s1, z0, z1 = geom.panel_bounds(r, c)
            corners = geom.surface(np.array([s0, s1, s1, s0]), np.array([z0, z0, z1, z1]), np.zeros(4))
            shade = 1.0 + style.interior_variation * rng.uniform(-1.0, 1.0)
            out.append(
                Panel(
                    geom.index,
                    r,
                    c,
                    corners,
                    geom.normal(np.array(0.5 * (s0 + s1))),
                    np.clip(base * shade, 0.0, 1.0),
                    (r, c) not in unglazed,
                )
            )
    return out


def curve_segments(geom: PartGeometry, style: FacadeStyle, width_m: float) -> int:
    """Flat facets across ``width_m`` (m along the surface): 1 on a plane; on a cylinder enough that none
    turns through more than ``curve_max_facet_deg``."""
    p = geom.part
    if p.kind != "cylindrical":
        return 1
    return max(1, math.ceil(math.degrees(width_m / p.radius_m) / style.curve_max_facet_deg))


def part_meshes(
    geom: PartGeometry,
    style: FacadeStyle,
    first_panel: int,
    ground_z: float,
    rooms: dict[tuple[int, int], Room] | None = None,
    first_room: int = 0,
) -> tuple[TriMesh, TriMesh, TriMesh]:
    """(glass, frames, body) meshes of one part. Glass triangles carry their global panel index
    (``first_panel`` + row * cols + col); the body reaches down to world height ``ground_z``. The units
    (row, col) keyed in ``rooms`` have no glass: the body's front face is open behind them onto their room
    (its box and what it holds, part of the body mesh), numbered from ``first_room`` in sorted (row, col)
    order."""
    unglazed = frozenset(rooms or ())
    p, fw = geom.part, style.frame_width_m
    pitch = (p.width_m - fw) / p.cols
    seg = curve_segments(geom, style, pitch)  # per panel column
    h = (-style.frame_back_m, style.frame_depth_m)
    glass, frames = [], []
    for r in range(p.rows):
        for c in range(p.cols):
            if (r, c) in unglazed:
                continue
            s0, s1, z0, z1 = geom.panel_bounds(r, c)
            glass.append(
                sheet(geom.surface, (s0, s1), (z0, z1), seg, Material.GLASS, first_panel + r * p.cols + c)
            )
    for sk in geom.s_lines:
        frames.append(
            prism(geom.surface, (sk - fw / 2, sk + fw / 2), (0.0, p.height_m), h,
                  curve_segments(geom, style, fw), Material.FRAME)
        )
    for zk in geom.z_lines:
        for c in range(p.cols):
            s0, s1 = geom.s_lines[c] + fw / 2, geom.s_lines[c + 1] - fw / 2
            frames.append(prism(geom.surface, (s0, s1), (zk - fw / 2, zk + fw / 2), h, seg, Material.FRAME))
    z_floor = ground_z - geom.world_from_facade[2, 3]
    body = prism(
        geom.surface,
        (-p.width_m / 2, p.width_m / 2),
        (min(z_floor, 0.0), p.height_m),
        (-style.body_depth_m, -style.frame_back_m),
        seg * p.cols,
        Material.WALL,
    )
    if unglazed:
        body = _open_body(geom, style, body, seg * p.cols, min(z_floor, 0.0), rooms, first_room)
    return concat(glass), concat(frames), body


def _open_body(
    geom: PartGeometry,
    style: FacadeStyle,
    body: TriMesh,
    front_quads: int,
    z_floor: float,
    rooms: dict[tuple[int, int], Room],
    first_room: int,
) -> TriMesh:
    """The body with its front face (the first ``front_quads`` quads of its prism) rebuilt with a hole
    behind each unit keyed in ``rooms``, and its room behind each hole (numbered from ``first_room``)."""
    p = geom.part
    keep = np.arange(len(body.triangles)) >= 2 * front_quads
    units = sorted(rooms)
    holes = [geom.panel_bounds(r, c) for r, c in units]
    back = style.frame_back_m

    def front(s, z, hh):  # the body's front face as a sheet at h = 0
        return geom.surface(s, z, np.asarray(hh) - back)

    s_cuts = np.unique([-p.width_m / 2, p.width_m / 2, *[v for b in holes for v in b[:2]]])
    pieces = [body.select(keep)]
    for sa, sb in zip(s_cuts[:-1], s_cuts[1:], strict=True):
        over = [b for b in holes if b[0] <= sa and sb <= b[1]]
        z_cuts = np.unique([z_floor, p.height_m, *[v for b in over for v in b[2:]]])
        for za, zb in zip(z_cuts[:-1], z_cuts[1:], strict=True):
            if any(b[2] <= za and zb <= b[3] for b in over):
                continue
            seg = curve_segments(geom, style, sb - sa)
            pieces.append(sheet(front, (sa, sb), (za, zb), seg, Material.WALL))
    for k, (unit, (s0, s1, z0, z1)) in enumerate(zip(units, holes, strict=True)):
        pieces.append(room_mesh(geom, style, (s0, s1), (z0, z1), rooms[unit], first_room + k))
    return concat(pieces)


SHELF_HEIGHTS = (0.2, 0.45, 0.7)  # shelves' heights, fractions of the room's height (-)
SHELF_DEPTH = 0.3  # shelves' depth, a fraction of the room's (-)
ROOM_OBJECTS = 4  # object ids per room: walls, shelves, cloth, posts
OPENING_SAMPLES = 8  # cells per side of the grid over an opening through which a room's light is summed
FRONT_CLOTH = (0.1, 0.55, 0.3, 1.0)  # a cloth in the front half: (s0, s1, z0, z1), fractions of width, height
BACK_CLOTH_SPAN = ((0.0, 0.25), (0.75, 1.0), (0.4, 1.0))  # ranges of a back cloth's s0, s1, top (fractions)
POST_WIDTH = 0.06  # side of a post's square section, a fraction of the room's width (-)
# ranges of a post's centre: across the width, and back from the opening short of the shelves (fractions)
POST_SPAN = ((0.1, 0.9), (0.15, 0.6))
CLOTH_FOLDS = 24  # flat strips of a cloth (-)


def room_mesh(
    geom: PartGeometry,
    style: FacadeStyle,
    s: tuple[float, float],
    z: tuple[float, float],
    room: Room,
    index: int = 0,
) -> TriMesh:
    """A room behind the opening s x z of the body's front face: a box (floor, ceiling, side and back
    walls, seen from inside) holding what ``room`` drew: shelves along its back wall at ``room.shelves``,
    a cloth folded in waves in its front half or at its back wall (``room.cloth_at``), posts from floor
    to ceiling at ``room.posts``. Material INTERIOR, object id ``ROOM_OBJECTS * index`` + 0 (walls),
    1 (shelves), 2 (cloth), 3 (posts)."""
    back, depth = style.frame_back_m, style.room_depth_m
    h0, h1 = -back - depth, -back
    seg = curve_segments(geom, style, s[1] - s[0])
    first = ROOM_OBJECTS * index
    box = prism(geom.surface, s, z, (h0, h1), seg, Material.INTERIOR, first)
    # the box's front face closes the opening: the room is seen through where it was
    box = box.select(np.arange(len(box.triangles)) >= 2 * seg)
    height, width = z[1] - z[0], s[1] - s[0]
    thick = 0.04 * height
    shelves = [
        prism(geom.surface, s, (z[0] + f * height, z[0] + f * height + thick), (h0, h0 + SHELF_DEPTH * depth),
              seg, Material.INTERIOR, first + 1)
        for f in room.shelves
    ]
    pieces = [box, *shelves]
    if room.cloth_at == "front":
        # from the ceiling down to a third of the height over the left half, in deep vertical folds
        pieces.append(_cloth(geom, s, z, FRONT_CLOTH, h1 - 0.35 * depth, 0.04 * depth, first + 2))
    elif room.cloth_at == "back":
        # against the back wall, or in front of the shelves, from the floor, in shallow folds
        h = h0 + (SHELF_DEPTH * depth if room.shelves else 0.0) + 0.03 * depth
        pieces.append(_cloth(geom, s, z, room.cloth_span, h, 0.015 * depth, first + 2))
    side = POST_WIDTH * width
    for u, v in room.posts:
        sc, hc = s[0] + u * width, h1 - v * depth
        pieces.append(prism(geom.surface, (sc - side / 2, sc + side / 2), z, (hc - side / 2, hc + side / 2),
                            curve_segments(geom, style, side), Material.INTERIOR, first + 3))
    return concat(pieces)


def _cloth(
    geom: PartGeometry,
    s: tuple[float, float],
    z: tuple[float, float],
    span: tuple[float, float, float, float],
    h: float,
    fold: float,
    obj: int,
) -> TriMesh:
    """A cloth hanging over ``span`` (s0, s1, z0, z1: fractions of the opening s x z) at depth h, in
    vertical folds of amplitude ``fold`` (m), facing the opening."""
    width, height = s[1] - s[0], z[1] - z[0]
    n = CLOTH_FOLDS
    ss = np.linspace(s[0] + span[0] * width, s[0] + span[1] * width, n + 1)
    hh = h + fold * np.sin(ss / width * 2 * np.pi * 6)
    za, zb = z[0] + span[2] * height, z[0] + span[3] * height
    quads = np.stack([
        geom.surface(ss[:-1], np.full(n, za), hh[:-1]), geom.surface(ss[1:], np.full(n, za), hh[1:]),
        geom.surface(ss[1:], np.full(n, zb), hh[1:]), geom.surface(ss[:-1], np.full(n, zb), hh[:-1]),
    ], axis=1)
    mid = 0.5 * (ss[:-1] + ss[1:])
    out = geom.surface(mid, np.full(n, za), np.full(n, 1.0)) - geom.surface(mid, np.full(n, za), np.zeros(n))
    return quads_to_mesh(quads, out, Material.INTERIOR, obj)


@dataclass(frozen=True, eq=False)
class Room:
    """The room behind an unglazed unit, as the renderer lights it. Its opening, the hole in the body's
    front face, as ``corners`` [4, 3] (world, bottom-left, bottom-right, top-right, top-left seen from
    outside) and as ``cells`` [C, 3] (world centres of a grid over it), ``cell_normals`` [C, 3] (world,
    outward) and ``cell_areas`` [C] (m^2); the box's inner area ``box_area_m2`` (m^2, the opening
    included). Drawn per unit: the walls' albedo ``wall`` [3], the ``texture`` in [0, 1] (0 plain paint,
    bare shelves, a plain cloth; 1 mottled concrete, mixed things, a printed cloth) and the cloth's two
    colours ``cloth`` [2, 3]; what the box holds: the ``shelves``' heights (fractions of the room's
    height, of ``SHELF_HEIGHTS``), where the cloth hangs (``cloth_at``: none, in the front half at
    ``FRONT_CLOTH``, or at the back over ``cloth_span``: s0, s1, z0, z1 fractions of the opening) and the
    ``posts`` [P, 2] (centres: fraction of the width, fraction of the depth back from the opening)."""

    corners: np.ndarray
    cells: np.ndarray
    cell_normals: np.ndarray
    cell_areas: np.ndarray
    box_area_m2: float
    wall: np.ndarray
    texture: float
    cloth: np.ndarray
    shelves: tuple[float, ...]
    cloth_at: Literal["none", "front", "back"]
    cloth_span: tuple[float, float, float, float]
    posts: np.ndarray


def draw_room(
    geom: PartGeometry, style: FacadeStyle, row: int, col: int, rng: np.random.Generator
) -> Room:
    """The room behind unit (row, col) of ``geom``: its opening sampled on a grid of ``OPENING_SAMPLES``
    cells per side, and its style drawn from ``room_albedo`` and ``room_texture`` (uniform in each range),
    the walls grey with a slight tint, the cloth of any hue; then what it holds: ``room_shelves`` shelves
    at as many of ``SHELF_HEIGHTS`` drawn at random, a cloth in front or at the back with the chances of
    ``room_cloth`` (at the back over a span drawn in ``BACK_CLOTH_SPAN``), ``room_posts`` posts at centres
    drawn in ``POST_SPAN``."""
    s0, s1, z0, z1 = geom.panel_bounds(row, col)
    n, h = OPENING_SAMPLES, -style.frame_back_m
    se, ze = np.linspace(s0, s1, n + 1), np.linspace(z0, z1, n + 1)
    S, Z = np.meshgrid(se, ze, indexing="ij")  # [n + 1, n + 1] cell corners
    P = geom.surface(S, Z, np.full_like(S, h))
    d1, d2 = P[1:, 1:] - P[:-1, :-1], P[:-1, 1:] - P[1:, :-1]
    areas = 0.5 * np.linalg.norm(np.cross(d1, d2), axis=-1).ravel()
    sc, zc = np.meshgrid(0.5 * (se[1:] + se[:-1]), 0.5 * (ze[1:] + ze[:-1]), indexing="ij")
    cells = geom.surface(sc, zc, np.full_like(sc, h)).reshape(-1, 3)
    normals = geom.normal(sc).reshape(-1, 3)
    w, ht, d = s1 - s0, z1 - z0, style.room_depth_m
    grey = rng.uniform(*style.room_albedo)
    wall = np.clip(grey * (1.0 + rng.uniform(-0.06, 0.06, 3)), 0.0, 1.0)
    hue = rng.uniform(0.0, 2.0 * math.pi, 2)
    light = rng.uniform(0.3, 0.9, 2)
    chroma = rng.uniform(0.0, 0.35, 2)
    axes = np.array([0.0, 2.0 * math.pi / 3, 4.0 * math.pi / 3])
    cloth = np.clip(light[:, None] * (1.0 + chroma[:, None] * np.cos(hue[:, None] - axes)), 0.0, 1.0)
    corners = geom.surface(np.array([s0, s1, s1, s0]), np.array([z0, z0, z1, z1]), np.full(4, h))
    texture = float(rng.uniform(*style.room_texture))
    count = int(rng.integers(style.room_shelves[0], style.room_shelves[1] + 1))
    shelves = tuple(SHELF_HEIGHTS[k] for k in sorted(rng.choice(SHELVES_MAX, count, replace=False)))
    front, back = style.room_cloth
    u = rng.uniform()
    cloth_at = "front" if u < front else "back" if u < front + back else "none"
    (a0, a1), (b0, b1), (t0, t1) = BACK_CLOTH_SPAN
    span = (float(rng.uniform(a0, a1)), float(rng.uniform(b0, b1)), 0.0, float(rng.uniform(t0, t1)))
    posts = int(rng.integers(style.room_posts[0], style.room_posts[1] + 1))
    (u0, u1), (v0, v1) = POST_SPAN
    centres = np.stack([rng.uniform(u0, u1, posts), rng.uniform(v0, v1, posts)], axis=-1)
    return Room(corners, cells, normals, areas, 2.0 * (w * ht + w * d + ht * d), wall, texture, cloth,
                shelves, cloth_at, FRONT_CLOTH if cloth_at == "front" else span, centres)
