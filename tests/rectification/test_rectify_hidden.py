"""A dense coarse cloud holds the ground all around the facade; `rectify` leaves out the points the coarse
mesh hides from the camera, so the ground behind the facade cannot take the plane fit (with 150,000
environment points on demo, every frontal view was otherwise fitted to the wrong surface)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from facade_pipeline.config import default_params
from facade_pipeline.geometry.camera import PinholeCamera
from facade_pipeline.geometry.raycast import MeshRaycaster
from facade_pipeline.rectification.cylinder import SurfaceFitError, facing_points, fit_surface
from facade_pipeline.rectification.views import view_points
from stages import rectify

PARAMS = default_params("rectify", rectify.Params)
# the frontal views' footprint the fits below are measured at, the unit of the params' lengths: 6 m puts
# the occlusion margin at about 1 m and the loss scale at 5 cm
FOOTPRINT_M = 6.0
MARGIN_M = PARAMS.occlusion_margin * FOOTPRINT_M


def looking_at_facade(centre) -> PinholeCamera:
    """A camera at ``centre`` looking along -y (at a facade in the plane y = 0), z up, 160 x 120 px."""
    R = np.array([[-1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, -1.0, 0.0]])  # rows: right, down, forward
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = R, -R @ np.asarray(centre, float)
    K = np.array([[80.0, 0.0, 80.0], [0.0, 80.0, 60.0], [0.0, 0.0, 1.0]])
    return PinholeCamera(K, M, 160, 120)


def scene(seed=0):
    """A 30 m x 18 m facade at y = 0 as a two-triangle mesh, 1,500 points on it, and the ground behind it
    (z = 0, y from -100 to -2 m) with 20,000 points, as a dense cloud holds it."""
    rng = np.random.default_rng(seed)
    v = np.array([[-15.0, 0, 0], [15, 0, 0], [15, 0, 18], [-15, 0, 18]])
    f = np.array([[0, 1, 2], [0, 2, 3]])
    facade = np.stack([rng.uniform(-15, 15, 1500), rng.normal(0, 0.02, 1500), rng.uniform(0, 18, 1500)], 1)
    ground = np.stack([rng.uniform(-60, 60, 20000), rng.uniform(-100, -2, 20000), np.zeros(20000)], 1)
    return v, f, facade, ground


def test_points_hidden_by_the_coarse_mesh_are_left_out():
    v, f, facade, ground = scene()
    cam = looking_at_facade([0.0, 12.0, 9.0])
    mesh = MeshRaycaster(v, f)
    pts = np.vstack([facade, ground])
    everything = view_points(pts, cam)
    seen = view_points(pts, cam, mesh, MARGIN_M)
    assert (everything[:, 1] < -1).sum() > 5000  # the ground behind the facade projects into the view
    assert len(seen) > 1000 and np.all(seen[:, 1] > -1.0)  # none of it is kept, the facade's points are
    assert len(seen) == int((np.abs(everything[:, 1]) < 1).sum())
    # without a mesh, or with an infinite margin, nothing is left out
    assert len(view_points(pts, cam, mesh, np.inf)) == len(everything)


@pytest.mark.parametrize("height", [4.6, 13.4])
def test_the_facade_is_fitted_with_the_hidden_ground_left_out(height):
    v, f, facade, ground = scene()
    cam = looking_at_facade([-7.0, 12.0, height])
    mesh = MeshRaycaster(v, f)
    pts = view_points(np.vstack([facade, ground]), cam, mesh, MARGIN_M)
    fit = fit_surface(pts, cam.center, PARAMS.fit, FOOTPRINT_M)
    assert abs(fit.surface.normal @ [0.0, 1.0, 0.0]) > np.cos(np.radians(1.0))  # the facade's plane
    assert abs(fit.surface.radius_m) > 500 and fit.rms_m < 0.05


def curved_facade_with_ground_before(seed=0):
    """800 points on a 15 m cylinder (axis vertical at y = -15 m, apex at y = 0, +-0.6 rad, 18 m tall) and
    3,000 points of level ground before it (z = 0, y from 0.5 to 12 m): nothing hides the ground."""
    rng = np.random.default_rng(seed)
    th, z = rng.uniform(-0.6, 0.6, 800), rng.uniform(0, 18, 800)
    facade = np.stack([15 * np.sin(th), 15 * np.cos(th) - 15 + rng.normal(0, 0.02, 800), z], 1)
    ground = np.stack([rng.uniform(-20, 20, 3000), rng.uniform(0.5, 12, 3000), np.zeros(3000)], 1)
    return facade, ground


@pytest.mark.parametrize("height", [1.5, 3.0, 6.0])
def test_the_ground_before_the_facade_is_left_out_of_the_fit_from_a_low_camera(height):
    facade, ground = curved_facade_with_ground_before()
    cam = looking_at_facade([0.0, 12.0, height])
    pts = view_points(np.vstack([facade, ground]), cam)
    assert (pts[:, 2] < 0.01).sum() > len(pts) / 3  # the ground takes a third of the view's points or more
    fit = fit_surface(pts, cam.center, PARAMS.fit, FOOTPRINT_M, toward_camera=-cam.forward)
    assert fit.surface.radius_m == pytest.approx(15.0, rel=0.01) and fit.rms_m < 0.03
    assert abs(fit.surface.axis[2]) > np.cos(np.radians(1.0))  # the cylinder's axis is vertical
    assert fit.n_points == len(pts) and fit.n_inliers <= int((pts[:, 2] > 0.01).sum())
    # without the normals' test, ground and facade mix, the ground wins, or the split between them that the
    # optical axis leaves on the facade keeps a strip of it (127 points from 1.5 m): the radius is missed
    unfiltered = fit_surface(pts, cam.center, dataclasses.replace(PARAMS.fit, normal_knn=0), FOOTPRINT_M,
                             toward_camera=-cam.forward)
    assert unfiltered.surface.radius_m != pytest.approx(15.0, rel=0.01)


def test_facing_points_keeps_the_facade_and_drops_level_ground():
    facade, ground = curved_facade_with_ground_before()
    toward = np.array([0.0, 1.0, 0.0])
    keep = facing_points(np.vstack([facade, ground]), toward, 16, 60.0)
    assert keep[:800].mean() > 0.97 and keep[800:].mean() < 0.03
    assert facing_points(facade, toward, 0, 60.0).all()  # knn 0: every point is kept
    assert facing_points(facade[:2], toward, 16, 60.0).all()  # too few points for a normal


def test_a_view_of_level_ground_alone_is_refused_with_what_was_found():
    _, ground = curved_facade_with_ground_before()
    cam = looking_at_facade([0.0, 12.0, 1.5])
    pts = view_points(ground, cam)
    with pytest.raises(SurfaceFitError, match=r"faces the camera.*found 0 of"):
        fit_surface(pts, cam.center, PARAMS.fit, FOOTPRINT_M, "coarse_points.ply", toward_camera=-cam.forward)


def test_the_frontal_views_footprint_is_the_width_each_frames_on_the_mesh():
    """The unit of rectify's lengths: the median over the views of the width a view frames where its
    principal ray meets the coarse mesh (a camera 12 m from the facade, 160 px at f = 80 px, frames 24 m;
    one 6 m away, 12 m), views that miss the mesh left out; the same views of a facade 25 times the size
    give 25 times the footprint."""
    from facade_pipeline.rectification.surface_map import frontal_footprint_m

    v, f, _, _ = scene()
    cams = [looking_at_facade([0.0, 12.0, 9.0]), looking_at_facade([3.0, 6.0, 9.0]),
            looking_at_facade([5.0, 12.0, 9.0]), looking_at_facade([200.0, 12.0, 9.0])]  # the last misses
    mesh = MeshRaycaster(v, f)
    assert frontal_footprint_m(cams, lambda o, d: mesh.cast(o, d).t) == pytest.approx(24.0)
    big = MeshRaycaster(25 * v, f)
    far = [looking_at_facade(25 * c.center) for c in cams]
    assert frontal_footprint_m(far, lambda o, d: big.cast(o, d).t) == pytest.approx(25 * 24.0)
    assert np.isnan(frontal_footprint_m(cams[3:], lambda o, d: mesh.cast(o, d).t))
