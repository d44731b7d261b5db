"""The real-like effects (exposure spread, lens distortion, unglazed units, masts and cranes): each is
there when declared, and a scene that does not declare it is the scene without it (nothing is cast,
built or drawn for it)."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from facade_pipeline.errors import ConfigError
from facade_pipeline.io.colmap import undistort_options, undistort_rgb
from facade_pipeline.io.images import to_uint8
from facade_pipeline.synthetic.facade import BACK_CLOTH_SPAN, POST_SPAN, SHELF_HEIGHTS, draw_room
from facade_pipeline.synthetic.mesh import Material
from facade_pipeline.synthetic.noise import rng_for
from facade_pipeline.synthetic.params import SHELVES_MAX
from facade_pipeline.synthetic.render import first_hits, render_view, shade
from facade_pipeline.synthetic.scene import panels_description
from facade_pipeline.synthetic.simulate import build_simulator, raw_view, sensor_image, spread_stops
from facade_pipeline.synthetic.textures import opening_light, room_albedo, sun_through
from tests.synthetic.conftest import replace_in, shipped, tiny, with_effects, without


def test_the_shipped_real_like_scene_declares_the_four_effects():
    p = shipped("real_like")
    assert {"exposure_spread", "lens_distortion", "unglazed_units", "masts_and_cranes"} <= set(p.effects)


def test_exposure_spread_covers_its_range_and_clips_highlights():
    p = with_effects(tiny(uav_count=8), "exposure_spread")
    p = replace_in(p, "noise", exposure_spread_stops=(-1.0, 1.5))
    p = without(p, "sensor_noise")
    sim = build_simulator(p)
    image = np.full((8, 8, 3), 0.25, np.float32)
    image[0, 0] = 0.9  # a highlight: clips at every gain above 2^0.15
    stops = []
    for view in sim.views:
        raw = sensor_image(p, view, image).astype(float) / 255
        u = spread_stops(p, view)
        assert -1.0 <= u <= 1.5
        assert raw[1, 1, 0] == pytest.approx(min(0.25 * 2**u, 1.0), abs=1 / 255)
        if u > 0.2:
            assert raw[0, 0, 0] == 1.0
        stops.append(u)
    uav = [u for u, v in zip(stops, sim.views, strict=True) if v.kind == "uav"]
    assert min(uav) < -0.5 and max(uav) > 1.0  # spread over the range, not bunched
    off = without(p, "exposure_spread")
    for view in sim.views:
        assert np.array_equal(sensor_image(off, view, image), to_uint8(np.clip(image.astype(float), 0, 1)))


def test_a_lens_distorted_frontal_view_undistorts_to_its_truth_camera():
    p = replace_in(with_effects(tiny(size_px=192), "lens_distortion"), "noise", lens_k1_k2=(-0.2, 0.04))
    sim = build_simulator(p)
    off = build_simulator(without(p, "lens_distortion"))
    assert all(v.lens is None for v in off.views)
    assert all(v.lens is None for v in sim.views if v.kind == "uav")
    view = next(v for v in sim.views if v.kind == "frontal")
    assert view.lens is not None and (view.camera.width, view.camera.height) != (192, 192)
    raw = render_view(sim.scene, sim.tracer, sim.arrays, view.camera, 3, view.lens)
    assert raw.image.shape[:2] == (192, 192) and raw.material.shape == (view.camera.height, view.camera.width)
    # the glass seen through the lens, undistorted as the importer does, is the truth camera's glass
    hits = first_hits(sim.tracer, sim.arrays, *view.lens.pixel_rays(1), "other")
    seen = np.repeat((hits.material == Material.GLASS).reshape(192, 192, 1), 3, axis=2).astype(np.uint8) * 255
    undistorted = undistort_rgb(undistort_options(), seen, view.lens.colmap_camera())[..., 0] > 127
    truth = raw.material == Material.GLASS

    def iou(a, b):
        return (a & b).sum() / (a | b).sum()

    resized = cv2.resize(seen[..., 0], truth.shape[::-1], interpolation=cv2.INTER_NEAREST) > 127
    assert iou(undistorted, truth) > 0.95 and iou(resized, truth) < iou(undistorted, truth) - 0.02, (
        iou(undistorted, truth), iou(resized, truth))
    model = raw_view(p, view)
    assert model.radial == (-0.2, 0.04) and (model.camera.width, model.camera.height) == (192, 192)


def test_unglazed_units_are_openings_onto_a_room_and_not_panels():
    p = tiny()
    p = dataclasses.replace(p, effects=(*p.effects, "unglazed_units"),
                            facade=dataclasses.replace(p.facade, unglazed_units=((0, 1, 2),)))
    sim = build_simulator(p)
    scene = sim.scene
    ids = [i for i, pn in enumerate(scene.panels) if not pn.glazed]
    assert [(scene.panels[i].row, scene.panels[i].col) for i in ids] == [(1, 2)]
    glass = scene.mesh.material == Material.GLASS
    assert not np.isin(scene.mesh.object_id[glass], ids).any()
    described = panels_description(scene)
    assert len(described["panels"]) == len(scene.panels) - 1
    assert [(o["row"], o["col"]) for o in described["openings"]] == [(1, 2)]
    # a ray through the opening's centre enters the room (walls, shelves or cloth), none hits glass
    pn = scene.panels[ids[0]]
    view = next(v for v in sim.views if v.kind == "frontal" and 1 in v.block[1] and 2 in v.block[2])
    r = render_view(scene, sim.tracer, sim.arrays, view.camera, 1)
    uv, _ = view.camera.project(pn.corners)
    lo, hi = np.ceil(uv.min(axis=0)).astype(int) + 1, np.floor(uv.max(axis=0)).astype(int) - 1
    inside = r.material[lo[1]:hi[1], lo[0]:hi[0]]
    assert (inside == Material.INTERIOR).mean() > 0.95 and not (inside == Material.GLASS).any()
    plain = build_simulator(tiny()).scene
    assert not (plain.mesh.material == Material.INTERIOR).any()
    assert "openings" not in panels_description(plain)


def _opened(style_changes: dict | None = None, env_changes: dict | None = None):
    """A tiny scene with unit (1, 2) open onto a room, its facade style and environment changed."""
    p = tiny()
    facade = dataclasses.replace(p.facade, unglazed_units=((0, 1, 2),), **(style_changes or {}))
    return dataclasses.replace(p, effects=(*p.effects, "unglazed_units"), facade=facade,
                               environment=dataclasses.replace(p.environment, **(env_changes or {})))


def _floor_radiance(p, depths_m: np.ndarray) -> np.ndarray:
    """Radiance the renderer gives the room's floor at ``depths_m`` behind its opening, seen from 2 m in
    front of the opening's centre."""
    sim = build_simulator(p)
    geom = sim.scene.parts[0]
    s0, s1, z0, _ = geom.panel_bounds(1, 2)
    back = p.facade.frame_back_m
    eye = geom.surface(0.5 * (s0 + s1), z0 + 1.0, 2.0)
    target = geom.surface(np.full(len(depths_m), 0.5 * (s0 + s1)), np.full(len(depths_m), z0 + 0.01),
                          -back - depths_m)
    d = target - eye
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = np.broadcast_to(eye, d.shape).copy()
    hits = first_hits(sim.tracer, sim.arrays, o, d, "other")
    assert (hits.material == Material.INTERIOR).all() and (hits.object_id == 0).all()
    return shade(sim.scene, sim.tracer, sim.arrays, o, d).mean(axis=1)


def test_a_room_is_lit_through_its_opening_falling_with_depth_and_rising_with_the_sky():
    depths = np.array([0.3, 1.0, 1.8, 2.6])
    plain = {"room_texture": (0.0, 0.0), "room_albedo": (0.6, 0.6), "room_depth_m": 3.0, "room_posts": (0, 0)}
    shade = {"sun_intensity": 0.0}
    lit = _floor_radiance(_opened(plain, shade), depths)
    assert (np.diff(lit) < 0).all() and lit[-1] < 0.7 * lit[0], lit
    env = tiny().environment
    dim = {**shade, "sky_zenith_color": tuple(0.5 * c for c in env.sky_zenith_color),
           "sky_horizon_color": tuple(0.5 * c for c in env.sky_horizon_color)}
    np.testing.assert_allclose(_floor_radiance(_opened(plain, dim), depths), 0.5 * lit, rtol=1e-6)
    bright = _floor_radiance(_opened({**plain, "room_albedo": (0.9, 0.9)}, shade), depths)
    assert (bright > 1.5 * lit).all()  # a light box passes more of the light on: more than its albedo says


def test_the_sun_lights_a_room_where_its_ray_passes_through_the_opening():
    p = _opened({"room_depth_m": 3.0}, {"sun_azimuth_deg": 90.0, "sun_elevation_deg": 30.0})
    room = build_simulator(p).scene.rooms[0]
    geom = build_simulator(p).scene.parts[0]
    s0, s1, z0, z1 = geom.panel_bounds(1, 2)
    h = -p.facade.frame_back_m
    # the sun straight in front, 30 deg up: the ray from the floor's centre line at depth d leaves through
    # the opening while it rises less than the opening's height, d tan 30 < z1 - z0
    reach = (z1 - z0) / np.tan(np.radians(30.0))
    depths = np.array([0.2, 0.6, 0.9]) * min(reach, 3.0)
    floor = geom.surface(np.full(3, 0.5 * (s0 + s1)), np.full(3, z0), h - depths)
    up = np.tile([0.0, 0.0, 1.0], (3, 1))
    assert sun_through(floor, room, p.environment).all()
    deep = geom.surface(0.5 * (s0 + s1), z0, h - 1.1 * reach)[None]
    back = geom.surface(0.5 * (s0 + s1), z1 - 0.01, h - 0.5)[None]  # the ceiling's ray leaves downward
    assert not sun_through(deep, room, p.environment).any()
    assert not sun_through(back, room, p.environment).any()
    dark = dataclasses.replace(p.environment, sun_intensity=0.0)
    gain = opening_light(floor, up, room, p.environment) - opening_light(floor, up, room, dark)
    # the sun's Lambert term on the floor, plus the same share of its flux passed on by the walls at each
    assert np.ptp(gain) < 1e-9 and gain.min() > p.environment.sun_intensity * np.sin(np.radians(30.0))


def _corner_form_factor(a: float, b: float, d: float) -> float:
    """Form factor from a point to a parallel a x b rectangle at distance d facing it, the point opposite
    one of its corners."""
    x, y = a / d, b / d
    return (x / np.hypot(1, x) * np.arctan(y / np.hypot(1, x))
            + y / np.hypot(1, y) * np.arctan(x / np.hypot(1, y))) / (2 * np.pi)


def test_opening_light_is_the_form_factor_of_the_opening_times_what_it_shows():
    grey = (0.5, 0.5, 0.5)
    p = _opened({"room_albedo": (0.0, 0.0)},
                {"sky_zenith_color": grey, "sky_horizon_color": grey, "sun_intensity": 0.0})
    scene = build_simulator(p).scene
    room = scene.rooms[0]
    assert not room.wall.any()  # a black box passes nothing on: the light is the opening's alone
    geom = scene.parts[0]
    s0, s1, z0, z1 = geom.panel_bounds(1, 2)
    h = -p.facade.frame_back_m
    for d in (0.5, 1.5, 3.0):
        q = geom.surface(0.5 * (s0 + s1), 0.5 * (z0 + z1), h - d)[None]
        n = geom.normal(np.array([0.5 * (s0 + s1)]))
        got = opening_light(q, n, room, p.environment)[0]
        # each half is two of the four quarters the centre faces; the upper half shows the sky, the lower
        # half the ground's haze (0.6 of the horizon)
        half = 2 * _corner_form_factor((s1 - s0) / 2, (z1 - z0) / 2, d)
        np.testing.assert_allclose(got, half * 0.5 * (1.0 + 0.6), rtol=0.02)


def test_drawn_rooms_span_their_style_ranges_and_repeat_for_a_seed():
    p = _opened({"room_albedo": (0.2, 0.85), "room_texture": (0.1, 0.9)})
    geom = build_simulator(p).scene.parts[0]
    rooms = [draw_room(geom, p.facade, 1, 2, rng_for(7, "rooms", k)) for k in range(200)]
    grey = np.array([r.wall.mean() for r in rooms])
    texture = np.array([r.texture for r in rooms])
    assert 0.2 * 0.94 <= grey.min() < 0.26 and 0.79 < grey.max() <= 0.85 * 1.06, (grey.min(), grey.max())
    assert 0.1 <= texture.min() < 0.15 and 0.85 < texture.max() <= 0.9
    cloth = np.array([r.cloth for r in rooms])
    assert ((cloth >= 0) & (cloth <= 1)).all() and np.ptp(cloth[:, 0].mean(axis=1)) > 0.4
    again = draw_room(geom, p.facade, 1, 2, rng_for(7, "rooms", 0))
    assert again.texture == rooms[0].texture and np.array_equal(again.cloth, rooms[0].cloth)
    assert again.shelves == rooms[0].shelves and np.array_equal(again.posts, rooms[0].posts)


def _spans(values: np.ndarray, lo: float, hi: float) -> bool:
    """Whether ``values`` lie in [lo, hi] and reach within a tenth of the range of either end."""
    margin = 0.1 * (hi - lo)
    return lo <= values.min() < lo + margin and hi - margin < values.max() <= hi


def test_what_drawn_rooms_hold_spans_its_ranges():
    p = _opened({"room_shelves": (0, 3), "room_cloth": (0.3, 0.5), "room_posts": (0, 2)})
    geom = build_simulator(p).scene.parts[0]
    rooms = [draw_room(geom, p.facade, 1, 2, rng_for(7, "rooms", k)) for k in range(300)]
    assert len(SHELF_HEIGHTS) == SHELVES_MAX
    assert {len(r.shelves) for r in rooms} == {0, 1, 2, 3}
    assert set().union(*(r.shelves for r in rooms)) == set(SHELF_HEIGHTS)  # each height, not the lowest first
    at = np.array([r.cloth_at for r in rooms])
    assert abs((at == "front").mean() - 0.3) < 0.08 and abs((at == "back").mean() - 0.5) < 0.08
    assert abs((at == "none").mean() - 0.2) < 0.08
    back = np.array([r.cloth_span for r in rooms if r.cloth_at == "back"])
    for k, (lo, hi) in zip((0, 1, 3), BACK_CLOTH_SPAN, strict=True):
        assert _spans(back[:, k], lo, hi), (k, back[:, k].min(), back[:, k].max())
    assert (back[:, 2] == 0.0).all()  # from the floor
    assert {len(r.posts) for r in rooms} == {0, 1, 2}
    posts = np.concatenate([r.posts for r in rooms])
    for k, (lo, hi) in enumerate(POST_SPAN):
        assert _spans(posts[:, k], lo, hi), (k, posts[:, k].min(), posts[:, k].max())
    fixed = _opened({"room_shelves": (2, 2), "room_cloth": (0.0, 0.0), "room_posts": (1, 1)})
    room = draw_room(geom, fixed.facade, 1, 2, rng_for(7, "rooms"))
    assert len(room.shelves) == 2 and room.cloth_at == "none" and len(room.posts) == 1


def _through_the_opening(style: dict, n: int = 48):
    """Rays from 2 m in front of unit (1, 2)'s centre through an n x n grid over its opening, in a room of
    plain paint and no sun: the room's triangles by object id and the rays' hits, surface coordinates
    (s, z, h) and radiance [n, n] (grey)."""
    p = _opened({"room_texture": (0.0, 0.0), **style}, {"sun_intensity": 0.0})
    sim = build_simulator(p)
    geom = sim.scene.parts[0]
    s0, s1, z0, z1 = geom.panel_bounds(1, 2)
    ss, zz = np.meshgrid(np.linspace(s0, s1, n + 2)[1:-1], np.linspace(z0, z1, n + 2)[1:-1], indexing="ij")
    eye = geom.surface(0.5 * (s0 + s1), 0.5 * (z0 + z1), 2.0)
    d = geom.surface(ss.ravel(), zz.ravel(), np.full(n * n, -p.facade.frame_back_m)) - eye
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = np.broadcast_to(eye, d.shape).copy()
    hits = first_hits(sim.tracer, sim.arrays, o, d, "other")
    radiance = shade(sim.scene, sim.tracer, sim.arrays, o, d).mean(axis=1).reshape(n, n)
    room = sim.scene.mesh.object_id[sim.scene.mesh.material == Material.INTERIOR]
    return p, geom, room, hits, geom.surface_coords(hits.points), radiance


@pytest.mark.parametrize(("holds", "style"), [
    ("nothing", {}),
    ("shelves", {"room_shelves": (1, 1)}),
    ("a cloth in front", {"room_cloth": (1.0, 0.0)}),
    ("a cloth at the back", {"room_cloth": (0.0, 1.0)}),
    ("a post", {"room_posts": (1, 1)}),
])
def test_a_room_holding_nothing_renders_as_a_plain_box(holds, style):
    empty = {"room_shelves": (0, 0), "room_cloth": (0.0, 0.0), "room_posts": (0, 0)}
    p, geom, room, hits, (s, z, h), radiance = _through_the_opening({**empty, **style})
    s0, s1, z0, z1 = geom.panel_bounds(1, 2)
    h0 = -p.facade.frame_back_m - p.facade.room_depth_m
    tol = 1e-6
    on_box = (np.abs(h - h0) < tol) | (np.abs(s - s0) < tol) | (np.abs(s - s1) < tol)
    on_box |= (np.abs(z - z0) < tol) | (np.abs(z - z1) < tol)
    assert (hits.material == Material.INTERIOR).all()
    if holds != "nothing":
        # what it holds is in the mesh under its own object id and in sight through the opening
        assert set(np.unique(room)) == {0, {"shelves": 1, "a post": 3}.get(holds, 2)}
        assert (hits.object_id != 0).mean() > 0.01 and not on_box.all()
        return
    assert (room == 0).all() and (hits.object_id == 0).all() and on_box.all()
    # plain paint lit through the opening: across the back wall the radiance changes by a few per cent
    # from one ray to the next, no edge
    back = (np.abs(h - h0) < tol).reshape(radiance.shape)
    pair = back[1:] & back[:-1]
    step = np.abs(np.diff(radiance, axis=0))[pair] / radiance[1:][pair]
    assert pair.sum() > 100 and step.max() < 0.05, step.max()


def test_a_textured_room_is_rougher_than_a_plain_one():
    geom = build_simulator(_opened()).scene.parts[0]
    p = _opened()
    xs = np.linspace(0.0, 3.0, 400)
    pts = geom.surface(np.full_like(xs, 0.0), 1.0 + xs, np.full_like(xs, -1.0))
    spread = {}
    for t in (0.0, 1.0):
        room = dataclasses.replace(draw_room(geom, p.facade, 1, 2, rng_for(1, "rooms")), texture=t)
        spread[t] = [room_albedo(pts, np.full(len(xs), k), room, 3).std(axis=0).max() for k in (0, 1, 2)]
    assert spread[0.0][0] < 1e-9 and spread[0.0][1] < 1e-9  # plain paint, bare boards
    assert all(spread[1.0][k] > 0.02 for k in (0, 1)), spread


@pytest.mark.parametrize(("units", "effects", "named"), [
    (((0, 1, 2),), (), "synthesize.facade.unglazed_units"),
    (((0, 7, 0),), ("unglazed_units",), "synthesize.facade.unglazed_units[0]"),
    ((), ("unglazed_units",), "synthesize.facade.unglazed_units"),
])
def test_unglazed_units_name_the_key_when_wrong(units, effects, named):
    p = tiny()
    with pytest.raises(ConfigError) as e:
        facade = dataclasses.replace(p.facade, unglazed_units=units)
        dataclasses.replace(p, effects=(*p.effects, *effects), facade=facade)
    assert named in str(e.value)


@pytest.mark.parametrize(("key", "value"), [
    ("room_albedo", (0.8, 0.2)),
    ("room_texture", (0.8, 0.2)),
    ("room_shelves", (2, 1)),
    ("room_shelves", (0, SHELVES_MAX + 1)),
    ("room_cloth", (0.6, 0.5)),
    ("room_posts", (2, 1)),
])
def test_room_style_ranges_name_the_key_when_wrong(key, value):
    with pytest.raises(ConfigError) as e:
        _opened({key: value})
    assert f"synthesize.facade.{key}" in str(e.value)


def test_masts_and_cranes_stand_in_front_and_are_reflected_by_the_glass():
    p = replace_in(tiny(), "render", supersample=1)
    on, off = build_simulator(with_effects(p, "masts_and_cranes")), build_simulator(p)
    mast = on.scene.mesh.material == Material.MAST
    assert mast.any() and not (off.scene.mesh.material == Material.MAST).any()
    assert len(on.scene.placement.poles) == p.environment.pole_count and on.scene.placement.crane
    # everything else stays where it was: the masts are added after the other objects
    n = len(off.scene.mesh.triangles)
    assert np.array_equal(on.scene.mesh.vertices[on.scene.mesh.triangles[:n]],
                          off.scene.mesh.vertices[off.scene.mesh.triangles])
    assert on.scene.placement.trees == off.scene.placement.trees
    s = on.scene.site_xy(on.scene.mesh.vertices[on.scene.mesh.triangles[mast]].reshape(-1, 3))
    assert s[:, 1].min() > 0  # in front of the facade
    changed = 0
    for a, b in zip(on.views, off.views, strict=True):
        ra = render_view(on.scene, on.tracer, on.arrays, a.camera, 1)
        rb = render_view(off.scene, off.tracer, off.arrays, b.camera, 1)
        glass = ra.material == Material.GLASS
        assert np.array_equal(ra.material[glass], rb.material[glass])
        changed += int((np.abs(ra.image - rb.image).max(axis=2)[glass] > 1e-3).sum())
    assert changed > 0  # seen in the glass
