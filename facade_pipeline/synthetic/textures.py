"""Procedural albedo of every material at world hit points, the sky, and sun shading.

All functions are vectorised over N hit points and deterministic for a seed. Colours are linear RGB in
[0, 1]; the sky and the sun disc may exceed 1 (they saturate in the image).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from facade_pipeline.synthetic.facade import ROOM_OBJECTS, Room
from facade_pipeline.synthetic.mesh import Material
from facade_pipeline.synthetic.noise import fbm, lattice_random, value_noise
from facade_pipeline.synthetic.params import EnvironmentParams, FacadeStyle

GRASS_NOISE_M = 1.5  # feature size of grass mottling (m)
PAVING_TILE_M = 1.2  # side of plaza paving tiles (m)
LINE_WIDTH_M = 0.12  # width of painted lines on the road and court (m)
DASH_M = 3.0  # dash and gap length of the road's centre line (m)
COURT_CIRCLE_M = 1.8  # radius of the court's centre circle (m)
WINDOW_PITCH_M = (3.0, 3.5)  # horizontal and vertical window spacing on nearby buildings (m)
WINDOW_FILL = (0.6, 0.55)  # fraction of each pitch that is window (-)
WATER_RIPPLE_M = 0.35  # wavelength of the fountain's ripples (m)
# things on the shelves of a textured room: boxes, planks (0-1)
SHELF_ITEMS = ((0.55, 0.38, 0.2), (0.8, 0.78, 0.7), (0.25, 0.3, 0.45), (0.7, 0.2, 0.15))
SHELF_ITEM_M = 0.35  # width of the things on a shelf (m)
ROOM_MOTTLE = 0.4  # relative albedo swing of a room's walls at texture 1 (-)
ROOM_MOTTLE_M = 0.8  # feature size of the mottling (m)
SKY_SAMPLES = 8  # cosine-weighted directions per side of the grid that averages the light entering a room
ROOM_CHUNK = 4096  # room points lit at once: bounds memory by this times the opening's cells
CLOTH_STRIPE_M = 0.25  # stripe width of the cloth (m)


def sun_direction(env: EnvironmentParams) -> np.ndarray:
    """Unit world vector [3] toward the sun."""
    az, el = math.radians(env.sun_azimuth_deg), math.radians(env.sun_elevation_deg)
    return np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])


def sky(d: np.ndarray, env: EnvironmentParams) -> np.ndarray:
    """Radiance [N, 3] seen along unit directions d [N, 3]: horizon-to-zenith gradient in sqrt(d_z), a
    darker haze below the horizon, and the sun disc of angular radius ``sun_disc_deg``."""
    up = np.sqrt(np.clip(d[:, 2], 0.0, 1.0))[:, None]
    hor, zen = np.asarray(env.sky_horizon_color), np.asarray(env.sky_zenith_color)
    out = hor + (zen - hor) * up
    out = np.where(d[:, 2:3] < 0.0, 0.6 * hor, out)
    in_sun = d @ sun_direction(env) > math.cos(math.radians(env.sun_disc_deg))
    out[in_sun] = env.sun_color
    return out


def lighting(n: np.ndarray, env: EnvironmentParams) -> np.ndarray:
    """Light factor [N, 1] for unit normals n [N, 3] facing the viewer: ambient + sun Lambert term."""
    return (env.ambient + env.sun_intensity * np.clip(n @ sun_direction(env), 0.0, None))[:, None]


def _mix(a: np.ndarray, color, mask: np.ndarray) -> np.ndarray:
    return np.where(mask[:, None], np.asarray(color, dtype=np.float64), a)


def ground_albedo(xy: np.ndarray, env: EnvironmentParams, seed: int) -> np.ndarray:
    """Ground albedo [N, 3] at site-frame (x, y) [N, 2]: grass, paved plaza and fountain surround, a road
    parallel to the facade with edge lines and a dashed centre line, a blue court with white lines."""
    x, y = xy[:, 0], xy[:, 1]
    g = fbm(x / GRASS_NOISE_M, y / GRASS_NOISE_M, seed, 3)[:, None]
    out = np.asarray(env.grass_color) * (0.75 + 0.5 * g)
    fx, fy = env.fountain_center_m
    paved = (np.abs(y) < env.plaza_depth_m) | (np.hypot(x - fx, y - fy) < env.fountain_radius_m + 3.0)
    tile = lattice_random(np.floor(x / PAVING_TILE_M), np.floor(y / PAVING_TILE_M), seed + 1)[:, None]
    grout = (np.abs(x / PAVING_TILE_M - np.round(x / PAVING_TILE_M)) * PAVING_TILE_M < 0.03) | (
        np.abs(y / PAVING_TILE_M - np.round(y / PAVING_TILE_M)) * PAVING_TILE_M < 0.03
    )
    out = np.where(
        paved[:, None],
        np.asarray(env.paving_color) * (0.85 + 0.3 * tile) * np.where(grout, 0.7, 1.0)[:, None],
        out,
    )
    dy = y - env.road_distance_m
    road = np.abs(dy) < env.road_width_m / 2
    asphalt = np.asarray(env.road_color) * (0.8 + 0.4 * value_noise(x / 0.5, y / 0.5, seed + 2))[:, None]
    out = np.where(road[:, None], asphalt, out)
    edge = road & (np.abs(np.abs(dy) - (env.road_width_m / 2 - 0.4)) < LINE_WIDTH_M / 2)
    dash = road & (np.abs(dy) < LINE_WIDTH_M / 2) & (np.mod(x, 2 * DASH_M) < DASH_M)
    out = _mix(out, env.marking_color, edge | dash)
    return _court(out, x, y, env)


def _court(out: np.ndarray, x: np.ndarray, y: np.ndarray, env: EnvironmentParams) -> np.ndarray:
    (cx, cy), (cl, cw) = env.court_center_m, env.court_size_m
    u, v = x - cx, y - cy
    court = (np.abs(u) < cl / 2) & (np.abs(v) < cw / 2)
    out = _mix(out, env.court_color, court)
    w = LINE_WIDTH_M
    border = court & (
        (np.abs(u) > cl / 2 - 0.5 - w) & (np.abs(u) < cl / 2 - 0.5) & (np.abs(v) < cw / 2 - 0.5)
        | (np.abs(v) > cw / 2 - 0.5 - w) & (np.abs(v) < cw / 2 - 0.5) & (np.abs(u) < cl / 2 - 0.5)
    )
    centre = court & (np.abs(u) < w / 2) & (np.abs(v) < cw / 2 - 0.5)
    circle = court & (np.abs(np.hypot(u, v) - COURT_CIRCLE_M) < w / 2)
    return _mix(out, env.marking_color, border | centre | circle)


def building_albedo(
    p: np.ndarray, n: np.ndarray, obj: np.ndarray, env: EnvironmentParams, seed: int
) -> np.ndarray:
    """Nearby building walls [N, 3]: a colour per building and a grid of windows of varying brightness on
    vertical faces (face coordinates: horizontal along the face, z up); plain roofs."""
    pick = np.floor(lattice_random(obj, 0, seed) * len(env.building_colors)).astype(int)
    base = np.asarray(env.building_colors)[pick]
    t = np.stack([-n[:, 1], n[:, 0]], axis=1)
    u = np.einsum("ij,ij->i", p[:, :2], t) / np.maximum(np.linalg.norm(t, axis=1), 1e-9)
    fu, fv = np.mod(u / WINDOW_PITCH_M[0], 1.0), np.mod(p[:, 2] / WINDOW_PITCH_M[1], 1.0)
    window = (
        (np.abs(n[:, 2]) < 0.5)
        & (np.abs(fu - 0.5) < WINDOW_FILL[0] / 2)
        & (np.abs(fv - 0.55) < WINDOW_FILL[1] / 2)
        & (p[:, 2] > 1.0)
    )
    shade = 0.6 + 0.8 * lattice_random(
        np.floor(u / WINDOW_PITCH_M[0]) + 1000 * obj, np.floor(p[:, 2] / WINDOW_PITCH_M[1]), seed + 3
    )
    wall = base * (0.9 + 0.2 * value_noise(u / 2.0, p[:, 2] / 2.0, seed + 4))[:, None]
    return np.where(window[:, None], np.asarray(env.window_color) * shade[:, None], wall)


def albedo(
    mat: np.ndarray,
    p: np.ndarray,
    n: np.ndarray,
    obj: np.ndarray,
    site_xy: np.ndarray,
    env: EnvironmentParams,
    style: FacadeStyle,
    seed: int,
) -> np.ndarray:
    """Albedo [N, 3] of non-glass hits outside the rooms (``room_radiance`` lights those): material ids
    mat [N], world points p [N, 3], normals n [N, 3], object ids obj [N], site-frame ground coordinates
    site_xy [N, 2]."""
    out = np.zeros((len(mat), 3))
    uniform = {
        Material.FRAME: style.frame_color,
        Material.WALL: style.wall_color,
        Material.STONE: env.stone_color,
        Material.TRUNK: env.trunk_color,
        Material.CROWN: env.crown_color,
    }
    for m, color in uniform.items():
        sel = mat == m
        if m == Material.FRAME or not sel.any():
            out[sel] = color
            continue
        q = p[sel]
        out[sel] = (
            np.asarray(color)
            * (0.8 + 0.4 * fbm(q[:, 0] + q[:, 1] * 0.7, q[:, 2] + q[:, 1] * 0.3, seed + 5, 2))[:, None]
        )
    sel = mat == Material.GROUND
    out[sel] = ground_albedo(site_xy[sel], env, seed)
    sel = mat == Material.WATER
    r = np.hypot(*(site_xy[sel] - np.asarray(env.fountain_center_m)).T)
    out[sel] = np.asarray(env.water_color) * (0.8 + 0.2 * np.sin(2 * math.pi * r / WATER_RIPPLE_M))[:, None]
    sel = mat == Material.BUILDING
    out[sel] = building_albedo(p[sel], n[sel], obj[sel], env, seed)
    sel = mat == Material.MAST
    out[sel] = np.where((obj[sel] == 1)[:, None], np.asarray(env.crane_color), np.asarray(env.mast_color))
    return out


def room_albedo(p: np.ndarray, kind: np.ndarray, room: Room, seed: int) -> np.ndarray:
    """Albedo [N, 3] inside ``room`` at world points p [N, 3] of kind [N] (0 walls, 1 shelves, 2 cloth,
    3 posts: cast with the walls, in their concrete or paint). The room's texture t in [0, 1] blends a
    plain painted box (walls of one albedo, shelves bare boards of the walls' paint, a plain cloth) into
    mottled concrete (the walls' albedo swinging by
    ``ROOM_MOTTLE`` t), shelves of things of mixed colours and a cloth striped in its two colours."""
    t = room.texture
    q = p[:, 0] + p[:, 1]
    mottle = fbm(q / ROOM_MOTTLE_M, p[:, 2] / ROOM_MOTTLE_M, seed + 6, 2)
    wall = room.wall * (1.0 + ROOM_MOTTLE * t * (2.0 * mottle - 1.0))[:, None]
    pick = np.floor(lattice_random(np.floor(q / SHELF_ITEM_M), np.floor(p[:, 2] / 0.3), seed + 7)
                    * len(SHELF_ITEMS)).astype(int)
    shelf = (1.0 - t) * room.wall + t * np.asarray(SHELF_ITEMS)[pick]
    stripe = (np.floor(q / CLOTH_STRIPE_M) % 2 == 1)[:, None]
    cloth = np.where(stripe, (1.0 - t) * room.cloth[0] + t * room.cloth[1], room.cloth[0])
    return np.clip(np.where((kind == 1)[:, None], shelf, np.where((kind == 2)[:, None], cloth, wall)), 0, 1)


def _sky_without_sun(env: EnvironmentParams) -> EnvironmentParams:
    # the sun's disc is a point to the opening's grid of cells: summed over them it would light the room
    # in spots; its light is added apart, where its ray passes through the opening (``sun_through``)
    return replace(env, sun_disc_deg=0.0)


def sun_through(p: np.ndarray, room: Room, env: EnvironmentParams) -> np.ndarray:
    """Whether the ray from each room point p [N, 3] toward the sun leaves through the room's opening [N]
    (the opening taken as the plane quad of its corners: exact on a planar part, within the sagitta of a
    unit's width on a cylinder)."""
    s = sun_direction(env)
    c = room.corners
    m = room.cell_normals.mean(axis=0)
    along = float(s @ m)
    if along <= 1e-9:
        return np.zeros(len(p), bool)
    t = (c[0] - p) @ m / along
    x = p + t[:, None] * s - c[0]
    eu, ev = c[1] - c[0], c[3] - c[0]
    a, b = x @ eu / (eu @ eu), x @ ev / (ev @ ev)
    return (t > 0) & (a >= 0) & (a <= 1) & (b >= 0) & (b <= 1)


def opening_light(p: np.ndarray, n: np.ndarray, room: Room, env: EnvironmentParams) -> np.ndarray:
    """Light [N, 3] reaching room points p [N, 3] with unit normals n [N, 3] (facing into the room) through
    the room's opening, as radiance per unit albedo (a matte point's radiance is its albedo times this):
    the sky and the ground's haze seen through each cell of the opening, sum L cos_p cos_q A / (pi r^2)
    (the point-to-area form factor), plus the light the box's walls pass on, the flux that came in
    (pi A_open L_in, L_in the cosine-weighted mean radiance entering, the sun's share included) reflected
    on with the walls' mean albedo rho, a share 1 - f (f = A_open / A_box) staying inside each bounce,
    spread evenly over the box's inner area: rho (1 - f) L_in A_open / ((A_box - A_open) (1 - rho (1 - f)));
    plus the sun's Lambert term (``sun_intensity`` n . s, as outside) where the sun's ray leaves through the
    opening (the renderer casts no other shadow: shelves, cloth and posts do not shade each other)."""
    sun = env.sun_intensity * np.clip(n @ sun_direction(env), 0.0, None) * sun_through(p, room, env)
    sky_env = _sky_without_sun(env)
    out = np.empty((len(p), 3))
    for a in range(0, len(p), ROOM_CHUNK):
        v = room.cells[None] - p[a : a + ROOM_CHUNK, None]  # [N, C, 3]
        r2 = np.maximum(np.einsum("ncj,ncj->nc", v, v), 1e-12)
        w = v / np.sqrt(r2)[..., None]
        cos_p = np.clip(np.einsum("ncj,nj->nc", w, n[a : a + ROOM_CHUNK]), 0.0, None)
        cos_q = np.clip(np.einsum("ncj,cj->nc", w, room.cell_normals), 0.0, None)
        L = sky(w.reshape(-1, 3), sky_env).reshape(w.shape)
        out[a : a + ROOM_CHUNK] = np.einsum("ncj,nc->nj", L, cos_p * cos_q * room.cell_areas / (np.pi * r2))
    a_open = float(room.cell_areas.sum())
    f = a_open / room.box_area_m2
    rho = float(np.mean(room.wall))
    fill = rho * (1.0 - f) * a_open / ((room.box_area_m2 - a_open) * (1.0 - rho * (1.0 - f)))
    m = room.cell_normals.mean(axis=0)
    sun_in = env.sun_intensity * max(float(sun_direction(env) @ m) / float(np.linalg.norm(m)), 0.0)
    return out + fill * (_light_in(room, sky_env) + sun_in) + sun[:, None]


def _light_in(room: Room, env: EnvironmentParams) -> np.ndarray:
    """Cosine-weighted mean radiance [3] coming in through the opening: the outward hemisphere of its mean
    normal on a ``SKY_SAMPLES`` x ``SKY_SAMPLES`` grid even in projected solid angle."""
    m = room.cell_normals.mean(axis=0)
    m /= np.linalg.norm(m)
    u = np.cross(m, [0.0, 0.0, 1.0])
    u = u / np.linalg.norm(u) if np.linalg.norm(u) > 1e-6 else np.array([1.0, 0.0, 0.0])
    v = np.cross(m, u)
    k = (np.arange(SKY_SAMPLES) + 0.5) / SKY_SAMPLES
    r, phi = np.meshgrid(np.sqrt(k), 2.0 * np.pi * k, indexing="ij")
    r, phi = r.ravel(), phi.ravel()
    d = (r * np.cos(phi))[:, None] * u + (r * np.sin(phi))[:, None] * v + np.sqrt(1 - r * r)[:, None] * m
    return sky(d, env).mean(axis=0)


def room_radiance(
    p: np.ndarray, n: np.ndarray, obj: np.ndarray, rooms: tuple[Room, ...], env: EnvironmentParams, seed: int
) -> np.ndarray:
    """Radiance [N, 3] of room hits (material INTERIOR): world points p [N, 3], normals n [N, 3] facing
    the viewer (into the room), object ids obj [N] (``ROOM_OBJECTS`` per room, in ``rooms``' order): each
    room's albedo (``room_albedo``) times the light through its opening (``opening_light``)."""
    out = np.zeros((len(p), 3))
    k = obj // ROOM_OBJECTS
    for i, room in enumerate(rooms):
        sel = k == i
        if sel.any():
            out[sel] = room_albedo(p[sel], obj[sel] % ROOM_OBJECTS, room, seed) * opening_light(
                p[sel], n[sel], room, env)
    return out
