"""Rectification of a view of a cylinder: residual at the samples, straight panel edges, planar "
"pass-through."""

from __future__ import annotations

import numpy as np

from facade_pipeline.config import default_params
from facade_pipeline.geometry.camera import PinholeCamera, intrinsics, look_at
from facade_pipeline.geometry.cylinder import Surface
from facade_pipeline.geometry.rectification import rectify_view, warp_image
from facade_pipeline.segmentation.accuracy import line_deviation_px
from stages import rectify

WARP = default_params("rectify", rectify.Params).warp


def camera(W=96, H=80, eye=(0.0, 6.0, 3.0), target=(0.0, 0.0, 3.0), f=83.0):
    """60 deg horizontal field of view at f = 83 px, as the simulator's frontal views."""
    return PinholeCamera(intrinsics(f, f, W / 2, H / 2), look_at(np.array(eye), np.array(target)), W, H)


def cylinder(R=15.0):
    # axis along z at (0, -R); p0 = (0, 0, 0) faces +y (the camera)
    return Surface(np.zeros(3), np.array([0.0, 0, 1]), np.array([0.0, 1, 0]), 1.0 / R)


def test_curved_view_residual_and_straight_verticals_and_horizontals():
    cam, surf = camera(), cylinder()
    rect = rectify_view(cam, surf, WARP)
    assert rect.kind == "curved" and rect.max_shift_px > 1.0
    assert rect.forward.max_px < 0.5 and rect.inverse.max_px < 0.5
    R = 15.0
    for phi in (-0.25, 0.0, 0.2):  # rulings of the cylinder: vertical edges
        pts = np.stack(
            [np.full(20, -R * np.sin(phi)), np.full(20, R * np.cos(phi) - R), np.linspace(1, 5, 20)], 1
        )
        uv, _ = cam.project(pts)
        assert line_deviation_px(rect.forward(uv)) < 1.0
    for z in (1.5, 4.0):  # arcs at constant height: horizontal edges, curved in the view
        phi = np.linspace(-0.3, 0.3, 30)
        uv, _ = cam.project(np.stack([-R * np.sin(phi), R * np.cos(phi) - R, np.full(30, z)], 1))
        inside = (uv[:, 0] > 0) & (uv[:, 0] < cam.width)
        assert line_deviation_px(uv[inside]) > 0.5  # bowed before
        assert line_deviation_px(rect.forward(uv[inside])) < 0.1  # straight after


def test_tilted_axis_and_flat_patch_pass_through():
    cam = camera()
    flat = Surface(np.zeros(3), np.array([0.0, 0, 1]), np.array([0.0, 1, 0]), 1e-9)  # R = 1e9 m
    rect = rectify_view(cam, flat, WARP)
    assert rect.kind == "planar" and rect.forward.is_identity
    img = np.random.default_rng(0).integers(0, 255, (cam.height, cam.width, 3), dtype=np.uint8)
    assert np.array_equal(warp_image(img, rect), img)
    axis = np.array([0.3, 0.0, 1.0]) / np.linalg.norm([0.3, 0.0, 1.0])
    tilted = Surface(np.zeros(3), axis, np.array([0.0, 1, 0]), 1 / 15.0)
    rect = rectify_view(cam, tilted, WARP)
    assert rect.kind == "curved" and rect.forward.max_px < 0.5 and rect.inverse.max_px < 0.5


def test_extreme_unfolding_reports_its_residual():
    """A wide view (77 deg) close to a tight cylinder (R = 10 m): degree 7 cannot follow the unfolding at the
    image borders; the fit says so instead of hiding it."""
    rect = rectify_view(camera(f=60.0), cylinder(10.0), WARP)
    assert rect.max_shift_px > 30
    assert 0.5 < rect.forward.max_px < 5.0 and rect.forward.rms_px < rect.forward.max_px
