"""Metric rectification of frontal views: planes by their homography, cylinders unrolled; exact round trips,
straight panel edges, facade up = image up, left to right seen from outside, the scale, and the views that
are skipped (edge-on, too large)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from facade_pipeline.config import default_params
from facade_pipeline.geometry.camera import PinholeCamera, intrinsics, look_at
from facade_pipeline.rectification.cylinder import Surface
from facade_pipeline.rectification.surface_map import (
    Chart,
    ViewRectification,
    parallax_grid,
    rectify_view,
    valid_region,
    warp_image,
)
from facade_pipeline.segmentation.accuracy import line_deviation_px
from stages import rectify

PARAMS = default_params("rectify", rectify.Params)


def camera(W=96, H=80, eye=(0.0, 6.0, 3.0), target=(0.0, 0.0, 3.0), f=83.0):
    """60 deg horizontal field of view at f = 83 px, as the simulator's frontal views."""
    return PinholeCamera(intrinsics(f, f, W / 2, H / 2), look_at(np.array(eye), np.array(target)), W, H)


def cylinder(R=15.0):
    # axis along z at (0, -R); p0 = (0, 0, 0) faces +y (the camera)
    return Surface(np.zeros(3), np.array([0.0, 0, 1]), np.array([0.0, 1, 0]), 1.0 / R)


def plane():
    return Surface(np.zeros(3), np.array([1.0, 0, 0]), np.array([0.0, 1, 0]), 0.0)


def test_chart_point_and_coords_round_trip_for_every_curvature():
    rng = np.random.default_rng(0)
    s, h = rng.uniform(-3, 3, 50), rng.uniform(-3, 3, 50)  # |k s| < pi: one turn
    for k in (0.0, 1e-12, 1 / 15.0, -1 / 15.0, 1.0):
        chart = Chart(np.zeros(3), np.array([1.0, 0, 0]), np.array([0.0, 0, 1]), np.array([0.0, -1, 0]), k)
        p = chart.point(s, h)
        assert np.all(np.isfinite(p))
        s2, h2 = chart.coords(p)
        assert np.allclose(s2, s, atol=1e-9) and np.allclose(h2, h, atol=1e-12)
        if k != 0.0:  # on the cylinder: distance 1/|k| from the axis
            surf = chart.surface()
            assert np.abs(surf.signed_distance(p)).max() < 1e-9


@pytest.mark.parametrize("surface", [plane(), cylinder()], ids=["plane", "cylinder"])
def test_round_trip_up_right_and_scale(surface):
    cam = camera(eye=(2.0, 6.0, 1.0), target=(0.0, 0.0, 3.0))  # oblique, looking up
    rect = rectify_view(cam, surface, PARAMS)
    assert rect.kind == ("plane" if surface.curvature_per_m == 0 else "cylinder")
    rng = np.random.default_rng(1)
    uv = rng.uniform([5, 5], [cam.width - 5, cam.height - 5], (200, 2))
    back = rect.to_original(rect.to_rectified(uv))
    assert np.abs(back - uv).max() < 1e-6
    # a point higher on the facade is higher in the rectified image (smaller y); seen from outside (+y), -x
    # runs to the right, along the plane and along the cylinder's arc
    chart = rect.chart
    a = chart.point(np.array([0.0, 0.0]), np.array([2.0, 4.0]))
    b = chart.point(np.array([-1.0, 1.0]), np.array([3.0, 3.0]))
    ra, rb = rect.to_rectified(cam.project(a)[0]), rect.to_rectified(cam.project(b)[0])
    assert ra[1, 1] < ra[0, 1] and rb[1, 0] > rb[0, 0]
    assert chart.right[0] < -0.99 and chart.up[2] > 0.99
    # 1 m along the facade is 1 / metres_per_px pixels wherever it is
    for s0 in (-1.0, 0.5):
        p = chart.point(np.array([s0, s0 + 1.0]), np.array([3.0, 3.0]))
        r = rect.to_rectified(cam.project(p)[0])
        assert abs(np.linalg.norm(r[1] - r[0]) * rect.metres_per_px - 1.0) < 1e-9


def test_auto_scale_is_the_views_ground_sample_distance():
    cam = camera(f=83.0)  # 6 m from the plane, straight on: 6 / 83 m per px at the centre
    rect = rectify_view(cam, plane(), PARAMS)
    assert abs(rect.metres_per_px - 6.0 / 83.0) / (6.0 / 83.0) < 0.05
    fixed = rectify_view(cam, plane(), dataclasses.replace(PARAMS, metres_per_px=0.05))
    assert fixed.metres_per_px == 0.05 and abs(fixed.width / rect.width - rect.metres_per_px / 0.05) < 0.05


def test_plane_homography_is_the_exact_map():
    cam = camera(eye=(3.0, 5.0, 1.0))
    rect = rectify_view(cam, plane(), PARAMS)
    H = rect.homography()
    xy = np.random.default_rng(2).uniform(0, [rect.width, rect.height], (100, 2))
    q = np.c_[xy, np.ones(len(xy))] @ H.T
    assert np.allclose(q[:, :2] / q[:, 2:], rect.to_original(xy), atol=1e-8)


def test_cylinder_rulings_and_arcs_come_out_straight_and_the_polynomial_reports_its_residual():
    cam, surf, R = camera(), cylinder(), 15.0
    rect = rectify_view(cam, surf, PARAMS)
    fwd, inv = rect.polynomial
    assert fwd.degree == 7 and fwd.max_px < 0.5 and inv.max_px < 0.5
    for phi in (-0.25, 0.0, 0.2):  # rulings of the cylinder: vertical edges
        x, y = -R * np.sin(phi), R * np.cos(phi) - R
        pts = np.stack([np.full(20, x), np.full(20, y), np.linspace(1, 5, 20)], 1)
        r = rect.to_rectified(cam.project(pts)[0])
        assert np.ptp(r[:, 0]) < 1e-6
    for z in (1.5, 4.0):  # arcs at constant height: horizontal edges, curved in the view
        phi = np.linspace(-0.3, 0.3, 30)
        uv, _ = cam.project(np.stack([-R * np.sin(phi), R * np.cos(phi) - R, np.full(30, z)], 1))
        inside = (uv[:, 0] > 0) & (uv[:, 0] < cam.width)
        assert line_deviation_px(uv[inside]) > 0.5  # bowed before
        assert np.ptp(rect.to_rectified(uv[inside])[:, 1]) < 1e-6  # straight and level after


@pytest.mark.parametrize("radius", [np.inf, 15.0, 6.0])
def test_parallax_grid_is_the_shift_of_a_point_standing_proud_of_the_surface(radius):
    """A point e proud of the surface along its normal is seen (e / D) P px from its foot in the rectified
    image, D the camera's distance to the surface: checked against the point's ray (e = 0.1 mm) at every
    node seen at less than 75 deg. For a plane P is the distance from the camera's foot; on a tight
    cylinder (6 m, seen from 6 m, as curved12) it grows much faster than that toward the silhouette."""
    cam = camera()
    surf = plane() if np.isinf(radius) else cylinder(radius)
    rect = rectify_view(cam, surf, PARAMS)
    xs, ys, P = parallax_grid(rect, 8.0)
    c, m, e = rect.chart, rect.metres_per_px, 1e-4
    D = abs(float(surf.signed_distance(cam.center[None])[0]))
    gx, gy = np.meshgrid(xs, ys)
    s_m = rect.s0_m + gx.ravel() * m
    foot = c.point(s_m, rect.h0_m - gy.ravel() * m)
    phi = (c.curvature_per_m * s_m)[:, None]
    n = np.cos(phi) * c.normal + np.sin(phi) * c.right
    ray = foot - cam.center
    seen = -(ray * n).sum(1) > np.cos(np.radians(75.0)) * np.linalg.norm(ray, axis=1)
    shifted = rect.to_rectified(cam.project(foot + e * n)[0]) - np.stack([gx.ravel(), gy.ravel()], 1)
    assert seen.sum() > 20
    np.testing.assert_allclose(shifted[seen] * D / e, P.reshape(-1, 2)[seen], rtol=1e-3, atol=1e-3)
    s_c, h_c = c.coords(cam.center[None])
    from_foot = np.stack([gx.ravel() - (s_c[0] - rect.s0_m) / m, gy.ravel() - (rect.h0_m - h_c[0]) / m], 1)
    if np.isinf(radius):
        np.testing.assert_allclose(P.reshape(-1, 2), from_foot, atol=1e-6)
    elif radius == 6.0:
        assert np.abs(P.reshape(-1, 2)[seen, 0]).max() > 2.0 * np.abs(from_foot[seen, 0]).max()


def test_edge_on_and_too_large_views_are_skipped_with_the_reason():
    grazing = camera(eye=(8.0, 1.5, 3.0), target=(0.0, 0.0, 3.0))  # 79 deg from the normal
    rect = rectify_view(grazing, plane(), PARAMS)
    assert rect.kind == "skipped" and "edge-on" in rect.reason and not rect.rectified
    tiny = rectify_view(camera(), plane(), dataclasses.replace(PARAMS, metres_per_px=0.001))
    assert tiny.kind == "skipped" and "max_size_factor" in tiny.reason


def test_image_warp_valid_region_and_json_round_trip(tmp_path):
    cam = camera(eye=(2.0, 6.0, 2.0))
    rect = rectify_view(cam, cylinder(), PARAMS)
    img = np.random.default_rng(3).integers(0, 255, (cam.height, cam.width, 3), dtype=np.uint8)
    out = warp_image(img, rect)
    assert out.shape == (rect.height, rect.width, 3)
    valid = valid_region(rect)
    assert 0.5 < valid.mean() <= 1.0 and out[~valid].max(initial=0) <= 255
    rect.save(tmp_path / "m.json")
    d = json.loads((tmp_path / "m.json").read_text())
    assert d["kind"] == "cylinder" and d["metres_per_px"] == rect.metres_per_px and "polynomial" in d
    again = ViewRectification.load(tmp_path / "m.json")
    xy = np.array([[3.0, 4.0], [rect.width - 2.0, rect.height - 3.0]])
    assert np.allclose(again.to_original(xy), rect.to_original(xy))
    unrect = ViewRectification.unrectified(cam, 0.05, "no surface")
    assert np.array_equal(warp_image(img, unrect), img) and np.array_equal(unrect.to_rectified(xy), xy)


def test_facade_support_marks_where_the_coarse_mesh_lies_on_the_surface():
    """A coarse mesh covering only the left half of the plane seen (x < 0): the support is the left half of
    the canvas (the facade runs left to right seen from outside, which is -x here)."""
    from facade_pipeline.geometry.raycast import MeshRaycaster
    from facade_pipeline.rectification.surface_map import facade_support

    cam = camera()
    rect = rectify_view(cam, plane(), PARAMS)
    v = np.array([[-20.0, 0.0, -10.0], [0.0, 0.0, -10.0], [0.0, 0.0, 20.0], [-20.0, 0.0, 20.0]])
    mesh = MeshRaycaster(v, np.array([[0, 1, 2], [0, 2, 3]]))
    support = facade_support(rect, lambda o, d: mesh.cast(o, d).t, 0.1, step_px=1)
    xs = np.arange(rect.width) + 0.5
    world_x = rect.chart.point(rect.s0_m + xs * rect.metres_per_px, np.full(rect.width, 3.0))[:, 0]
    row = support[rect.height // 2]
    assert row[world_x < -0.2].all() and not row[world_x > 0.2].any()
    far = MeshRaycaster(v + [0.0, -1.0, 0.0], np.array([[0, 1, 2], [0, 2, 3]]))  # 1 m behind: not the facade
    assert not facade_support(rect, lambda o, d: far.cast(o, d).t, 0.1).any()
    unrect = ViewRectification.unrectified(cam, 0.05, "no surface")
    assert facade_support(unrect, lambda o, d: mesh.cast(o, d).t, 0.1).all()


@pytest.mark.parametrize("surface", [plane(), cylinder()], ids=["plane", "cylinder"])
def test_a_canvas_bounded_in_s_spans_that_range_and_keeps_the_map(surface):
    cam = camera()
    full = rectify_view(cam, surface, PARAMS)
    s_lo = full.s0_m + 0.2 * full.width * full.metres_per_px  # a part's end inside the view
    part = rectify_view(cam, surface, PARAMS, (s_lo, np.inf))
    assert part.s0_m == pytest.approx(s_lo) and part.metres_per_px == full.metres_per_px
    assert part.width == pytest.approx(0.8 * full.width, abs=1)
    assert part.height == full.height
    # the same point of the view lands on the same point of the surface, shifted by the cut
    uv = np.array([[60.0, 30.0], [80.0, 50.0]])
    shift = (s_lo - full.s0_m) / full.metres_per_px
    assert np.allclose(part.to_rectified(uv), full.to_rectified(uv) - [shift, 0.0], atol=1e-6)
