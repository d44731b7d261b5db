"""Procedural albedo of every material at world hit points, the sky, and sun shading.

All functions are vectorised over N hit points and deterministic for a seed. Colours are linear RGB in
[0, 1]; the sky and the sun disc may exceed 1 (they saturate in the image).
"""

from __future__ import annotations

import math

import numpy as np

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
ROOM_WALL = (0.5, 0.48, 0.45)  # bare concrete of a room behind an unglazed unit (0-1)
ROOM_LIGHT = 0.55  # light reaching a room's inside, a fraction of the outside's (-)
# things on the shelves: boxes, planks (0-1)
SHELF_ITEMS = ((0.55, 0.38, 0.2), (0.8, 0.78, 0.7), (0.25, 0.3, 0.45), (0.7, 0.2, 0.15))
SHELF_ITEM_M = 0.35  # width of the things on a shelf (m)
CLOTH = ((0.85, 0.85, 0.8), (0.2, 0.35, 0.6))  # a dust sheet's two stripe colours (0-1)
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
    """Albedo [N, 3] of non-glass hits: material ids mat [N], world points p [N, 3], normals n [N, 3],
    object ids obj [N], site-frame ground coordinates site_xy [N, 2]."""
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
    sel = mat == Material.INTERIOR
    if sel.any():
        out[sel] = interior_albedo(p[sel], obj[sel], seed)
    sel = mat == Material.MAST
    out[sel] = np.where((obj[sel] == 1)[:, None], np.asarray(env.crane_color), np.asarray(env.mast_color))
    return out


def interior_albedo(p: np.ndarray, obj: np.ndarray, seed: int) -> np.ndarray:
    """A room behind an unglazed unit [N, 3], dimmed by ``ROOM_LIGHT``: mottled concrete walls (object
    0), things of mixed colours along the shelves (1), a striped cloth (2)."""
    q = p[:, 0] + p[:, 1]
    wall = np.asarray(ROOM_WALL) * (0.75 + 0.5 * fbm(q / 0.8, p[:, 2] / 0.8, seed + 6, 2))[:, None]
    pick = np.floor(lattice_random(np.floor(q / SHELF_ITEM_M), np.floor(p[:, 2] / 0.3), seed + 7)
                    * len(SHELF_ITEMS)).astype(int)
    items = np.asarray(SHELF_ITEMS)[pick]
    stripe = (np.floor(q / CLOTH_STRIPE_M) % 2).astype(int)
    cloth = np.asarray(CLOTH)[stripe]
    out = np.where((obj == 1)[:, None], items, np.where((obj == 2)[:, None], cloth, wall))
    return ROOM_LIGHT * out
