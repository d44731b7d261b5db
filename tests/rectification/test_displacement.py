"""The bound on a rectification's warp displacement: a fit whose map moves pixels of the view further than
the view's size (at the view's own scale, beyond a rotation, scale and shift) is not the surface the view
frames, and the view gets no surface with the reason, even where a coarse ``metres_per_px`` keeps the
rectified image small enough to pass ``max_size_factor``."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from facade_pipeline.config import default_params
from facade_pipeline.geometry.camera import PinholeCamera, intrinsics, look_at
from facade_pipeline.geometry.raycast import MeshRaycaster
from facade_pipeline.io.images import write_image
from facade_pipeline.rectification.cylinder import Surface, implausible_displacement
from facade_pipeline.rectification.surface_map import frontal_footprint_m, warp_displacement_px
from facade_pipeline.scene import View
from stages import rectify

PARAMS = default_params("rectify", rectify.Params)
W, H = 96, 80


def camera(yaw_deg: float = 0.0, roll_deg: float = 0.0, distance_m: float = 6.0) -> PinholeCamera:
    """A 60 deg camera at ``distance_m`` from the plane y = 0, turned ``yaw_deg`` about the vertical and
    rolled ``roll_deg`` about its optical axis, looking at (0, 0, 3)."""
    a = np.radians(yaw_deg)
    eye = np.array([distance_m * np.sin(a), distance_m * np.cos(a), 3.0])
    M = look_at(eye, np.array([0.0, 0.0, 3.0]))
    r = np.radians(roll_deg)
    roll = np.array([[np.cos(r), -np.sin(r), 0.0], [np.sin(r), np.cos(r), 0.0], [0.0, 0.0, 1.0]])
    M[:3] = roll @ M[:3]
    return PinholeCamera(intrinsics(83.0, 83.0, W / 2, H / 2), M, W, H)


def plane() -> Surface:
    return Surface(np.zeros(3), np.array([1.0, 0, 0]), np.array([0.0, 1, 0]), 0.0)


def test_displacement_is_zero_straight_on_whatever_the_roll_and_grows_with_obliquity():
    assert warp_displacement_px(camera(), plane()) < 1e-6
    assert warp_displacement_px(camera(roll_deg=90.0), plane()) < 1e-6  # a portrait photo
    assert warp_displacement_px(camera(roll_deg=180.0), plane()) < 1e-6
    shifts = [warp_displacement_px(camera(yaw), plane()) for yaw in (20.0, 35.0, 45.0, 60.0)]
    assert all(a < b for a, b in zip(shifts, shifts[1:], strict=False)), shifts
    assert 5.0 < shifts[0] < 0.3 * W and shifts[-1] > 3 * W, shifts
    # a surface that no ray of the view meets moves nothing it could measure
    behind = Surface(np.array([0.0, 50.0, 0.0]), np.array([1.0, 0, 0]), np.array([0.0, -1, 0]), 0.0)
    assert np.isnan(warp_displacement_px(camera(), behind))


def test_implausible_displacement_says_how_far_and_the_key():
    fit = dataclasses.replace(PARAMS.fit, max_displacement_size=1.0)
    assert implausible_displacement(0.9 * W, W, H, fit) is None
    why = implausible_displacement(1.5 * W, W, H, fit)
    assert "144 px" in why and "max_displacement_size = 1 x" in why and "96 x 80" in why
    assert implausible_displacement(float("nan"), W, H, fit) is not None
    tight = dataclasses.replace(fit, max_displacement_size=0.1)
    assert implausible_displacement(0.2 * W, W, H, tight) is not None


def _scene(layout, cam: PinholeCamera):
    """A 30 m x 18 m facade in the plane y = 0 (mesh and 3,000 points on it) and the view's image."""
    rng = np.random.default_rng(0)
    v = np.array([[-15.0, 0, -6], [15, 0, -6], [15, 0, 12], [-15, 0, 12]])
    mesh = MeshRaycaster(v, np.array([[0, 1, 2], [0, 2, 3]]))
    pts = np.stack([rng.uniform(-15, 15, 3000), rng.normal(0, 0.01, 3000), rng.uniform(-6, 12, 3000)], 1)
    view = View("f.png", "f", "frontal", cam, "01_import/frontal/images/f.png")
    image = layout.import_frontal_image(view.stem)
    image.parent.mkdir(parents=True, exist_ok=True)
    write_image(image, rng.integers(0, 256, (H, W, 3), dtype=np.uint8))
    return view, pts, mesh


#: (yaw, bound, what the view becomes): at the default bound (2) a plane seen 40 deg off its normal is
#: rectified, one seen 60 deg off gets no surface
CASES = [(20.0, 2.0, "plane"), (40.0, 2.0, "plane"), (40.0, 0.1, "unrectified"), (55.0, 1.0, "unrectified"),
         (60.0, 2.0, "unrectified")]  # fmt: skip


@pytest.mark.parametrize(("yaw_deg", "limit", "kind"), CASES)
def test_a_fit_whose_map_moves_pixels_too_far_gets_no_surface_with_the_reason(layout, yaw_deg, limit, kind):
    """The plane is fitted either way; only the bound on its map decides (a coarse metres_per_px keeps the
    rectified image far under max_size_factor)."""
    params = dataclasses.replace(
        PARAMS, metres_per_px=0.5, fit=dataclasses.replace(PARAMS.fit, max_displacement_size=limit)
    )
    view, pts, mesh = _scene(layout, camera(yaw_deg))
    unit = frontal_footprint_m([view.camera], lambda o, d: mesh.cast(o, d).t)  # as the stage measures it
    _, metrics = rectify.rectify_one(layout, view, pts, params, mesh, 1.0, unit)
    assert metrics["kind"] == kind, metrics
    shift = metrics["displacement_px"]
    assert shift is not None and shift > 5.0
    if kind == "unrectified":
        assert metrics["fit"].startswith("no surface: implausible fit, its map moves pixels up to")
        assert f"max_displacement_size = {limit:g} x the view's 96 x 80 px" in metrics["reason"]
        assert metrics["metres_per_px"] is not None  # the coarse mesh's scale, as for any view without one
    else:
        assert metrics["fit"] == "fitted" and shift < limit * W
