"""Robust cylinder fit and the stable surface form: hard cases (near-planar, too few points,
points on one line, non-vertical axis, ghost outliers)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from facade_pipeline.config import default_params
from facade_pipeline.rectification.cylinder import (
    Surface,
    SurfaceFitError,
    _stable_distance,
    fit_surface,
    implausible,
    point_parts,
)
from stages import rectify

FIT = default_params("rectify", rectify.Params).fit
# the frontal views' footprint these surfaces stand in, the unit of the fit's lengths: 6 m puts them at
# about 0.2 m of spread, a 0.5 m RANSAC threshold and a 5 cm loss scale
FOOTPRINT_M = 6.0


def cylinder_points(radius: float, rotvec=(0.0, 0.0, 0.0), n=800, width=7.0, height=6.0, noise=0.01, seed=1):
    """Points on a convex cylinder patch facing +y (axis along z before ``rotvec``), and the rotation."""
    rng = np.random.default_rng(seed)
    phi = rng.uniform(-0.5, 0.5, n) * width / abs(radius)
    z = rng.uniform(0, height, n)
    pts = np.stack([radius * np.sin(phi), radius * np.cos(phi) - radius, z], 1) + rng.normal(0, noise, (n, 3))
    R = Rotation.from_rotvec(rotvec).as_matrix()
    return pts @ R.T, R


def test_fits_radius_and_axis_despite_ghost_points():
    pts, _ = cylinder_points(15.0)
    ghosts = np.random.default_rng(2).uniform([-3, -30, 0], [3, -5, 6], (400, 3))  # mirrored behind glass
    fit = fit_surface(np.vstack([pts, ghosts]), np.array([0.0, 10.0, 3.0]), FIT, FOOTPRINT_M)
    assert fit.surface.radius_m == pytest.approx(15.0, rel=0.02)
    assert abs(fit.surface.axis @ [0, 0, 1]) > np.cos(np.radians(1.0))
    assert fit.rms_m < 0.02 and fit.n_inliers >= 780


def test_non_vertical_axis():
    pts, R = cylinder_points(12.0, rotvec=(0.4, 0.0, 0.2))
    fit = fit_surface(pts, R @ np.array([0.0, 10.0, 3.0]), FIT, FOOTPRINT_M)
    assert fit.surface.radius_m == pytest.approx(12.0, rel=0.02)
    assert abs(fit.surface.axis @ R[:, 2]) > np.cos(np.radians(1.0))


@pytest.mark.parametrize("radius", [1e3, 1e6, 1e12, 1e300])
def test_nearly_planar_points_stay_finite(radius):
    pts, _ = cylinder_points(radius)
    fit = fit_surface(pts, np.array([0.0, 10.0, 3.0]), FIT, FOOTPRINT_M)
    s = fit.surface
    assert np.isfinite(s.curvature_per_m) and abs(s.curvature_per_m) < 1e-2  # radius > 100 m
    assert np.all(np.isfinite(s.signed_distance(pts)))
    lam = s.intersect(np.array([[0.0, 10.0, 3.0]]), np.array([[0.0, -1.0, 0.0]]))
    assert lam[0] == pytest.approx(10.0, abs=0.05)


def test_too_few_points_and_points_on_a_line_are_typed_errors():
    pts, _ = cylinder_points(15.0, n=10)
    with pytest.raises(SurfaceFitError, match="at least 30 coarse points.*found 10") as e:
        fit_surface(pts, np.array([0.0, 10.0, 3.0]), FIT, FOOTPRINT_M, source="coarse_points.ply")
    assert e.value.path.name == "coarse_points.ply"
    line = np.stack([np.linspace(0, 5, 100), np.zeros(100), np.zeros(100)], 1) + 1e-4
    with pytest.raises(SurfaceFitError, match="one line"):
        fit_surface(line, np.array([0.0, 10.0, 3.0]), FIT, FOOTPRINT_M)


def test_stable_distance_matches_the_exact_formula_and_the_plane_limit():
    rng = np.random.default_rng(0)
    t, w = rng.uniform(-5, 5, 50), rng.uniform(-1, 1, 50)
    for k in (1 / 15.0, -1 / 7.0):
        exact = np.sign(k) * (np.hypot(w + 1 / k, t) - 1 / abs(k))
        assert np.allclose(_stable_distance(t, w, k), exact, atol=1e-12)
    assert np.array_equal(_stable_distance(t, w, 0.0), w)
    s = Surface(np.zeros(3), np.array([0.0, 0, 1]), np.array([0.0, 1, 0]), 1 / 15.0)
    assert Surface.from_dict(s.to_dict()).radius_m == pytest.approx(15.0)


def test_fits_that_cannot_be_a_facade_are_named():
    """An upright facade passes; a cylinder lying down (axis 26 deg off up), one tight against the width the
    view frames (a column or a chair before the camera) and a loose fit to clutter do not, with reasons."""
    pts, _ = cylinder_points(12.0)
    fit = fit_surface(pts, np.array([0.0, 10.0, 3.0]), FIT, FOOTPRINT_M)
    assert implausible(fit, 8.0, FIT) is None
    pts, R = cylinder_points(12.0, rotvec=(np.radians(26.0), 0.0, 0.0))
    fit = fit_surface(pts, R @ np.array([0.0, 10.0, 3.0]), FIT, FOOTPRINT_M)
    assert "cylinder axis 26 deg from up" in implausible(fit, 8.0, FIT)
    pts, _ = cylinder_points(1.0, width=2.5, noise=0.002)  # 2.5 m of arc on a 1 m radius
    fit = fit_surface(pts, np.array([0.0, 10.0, 1.0]), FIT, FOOTPRINT_M)
    assert fit.surface.radius_m == pytest.approx(1.0, rel=0.05)
    assert implausible(fit, 1.5, FIT) is None  # a column framed closely is a plausible (narrow) facade
    assert "an object, not a facade" in implausible(fit, 6.0, FIT)  # framed in a 6 m wide view
    floor, _ = cylinder_points(1e9, rotvec=(np.pi / 2, 0.0, 0.0), noise=0.0)  # a horizontal plane
    fit = fit_surface(floor, np.array([0.0, 3.0, 10.0]), FIT, FOOTPRINT_M, curved=False)
    assert "plane normal 90 deg from horizontal" in implausible(fit, 8.0, FIT)
    rng = np.random.default_rng(3)
    clutter = np.stack([rng.uniform(-3, 3, 500), rng.normal(0, 0.6, 500), rng.uniform(0, 6, 500)], 1)
    loose = dataclasses.replace(FIT, ransac_threshold=5.0 / FOOTPRINT_M, inlier_scale=1.0 / FOOTPRINT_M)
    fit = fit_surface(clutter, np.array([0.0, 10.0, 3.0]), loose, FOOTPRINT_M, curved=False)  # fmt: skip
    assert "clutter" in implausible(fit, 6.0, FIT)


def cylinder_beside_plane(x_plane, phi_cyl, radius=9.0, noise=0.03, density=25.0, height=6.0, seed=3):
    """Points on a plane y = 0 over ``x_plane`` (m) and on a convex cylinder tangent to y = 0 at x = 4.6
    over the angles ``phi_cyl`` (rad from +y, toward +x), its end at the plane's side set back from it
    (a curved part's end beside a planar part), noise at 3/5 of the loss scale as the coarse cloud's."""
    rng = np.random.default_rng(seed)
    n = int((x_plane[1] - x_plane[0]) * height * density)
    plane = np.stack([rng.uniform(*x_plane, n), np.zeros(n), rng.uniform(0, height, n)], 1)
    m = int(radius * (phi_cyl[1] - phi_cyl[0]) * height * density)
    phi = rng.uniform(*phi_cyl, m)
    cyl = np.stack([4.6 + radius * np.sin(phi), radius * (np.cos(phi) - 1.0), rng.uniform(0, height, m)], 1)
    return np.vstack([plane, cyl]) + rng.normal(0, noise, (n + m, 3))


@pytest.mark.parametrize(("x_plane", "phi_cyl", "eye", "radius"), [
    ((-3.5, -1.2), (-0.39, 0.35), (3.5, 7.0, 3.0), 9.0),  # the cylinder framed, the plane's end beside it
    ((-7.0, -1.2), (-0.39, -0.28), (-4.0, 7.0, 3.0), np.inf),  # the plane framed, the cylinder's end beside
])
def test_a_view_of_a_cylinder_beside_a_plane_fits_the_part_it_frames(x_plane, phi_cyl, eye, radius):
    """One surface bent through both parts fits neither: a plane through the cylinder and the plane's end,
    or a cylinder through the plane and the cylinder's end (46 m, five times the cylinder's radius)."""
    pts = cylinder_beside_plane(x_plane, phi_cyl)
    eye = np.array(eye)
    forward = np.array([pts[:, 0].mean() - eye[0], -eye[1], 0.0])
    fit = fit_surface(pts, eye, FIT, FOOTPRINT_M, toward_camera=-forward / np.linalg.norm(forward))
    on_plane = np.abs(pts[:, 1]) < 0.15  # the cylinder's end lies 0.65 m behind the plane
    main = on_plane if np.isinf(radius) else pts[:, 0] > 0.0
    assert fit.surface.radius_m == pytest.approx(radius, rel=0.02)
    assert fit.n_inliers == pytest.approx(main.sum(), rel=0.01)
    assert np.sqrt(np.mean(fit.surface.signed_distance(pts[main]) ** 2)) < 0.04


def test_points_apart_are_separate_parts_even_with_a_stray_point_between():
    rng = np.random.default_rng(4)
    left = rng.uniform([-6, 0, 0], [-2, 0.05, 6], (300, 3))
    right = rng.uniform([2, 0, 0], [6, 0.05, 6], (300, 3))
    stray = np.array([[0.0, 0.0, 3.0]])  # nearest to both surfaces, among neither's nearest
    labels = point_parts(np.vstack([left, right, stray]), 16)
    assert len(set(labels[:300])) == 1 and len(set(labels[300:600])) == 1
    assert len({labels[0], labels[300], labels[600]}) == 3
    assert np.all(point_parts(left, 0) == 0)


@pytest.mark.parametrize("radius", [np.inf, 9.0])
def test_one_surface_with_a_gap_is_fitted_over_both_sides(radius):
    """A plane or a cylinder whose points a gap splits (a pilaster, a strip the mesh hides) is one surface:
    the part fitted alone holds the other side too, and the fit over both stands."""
    rng = np.random.default_rng(5)
    s = np.concatenate([rng.uniform(-3.5, -1.0, 400), rng.uniform(1.0, 3.5, 400)])  # a 2 m gap
    z = rng.uniform(0.0, 6.0, 800)
    phi = s / radius
    pts = np.stack([radius * np.sin(phi), radius * (np.cos(phi) - 1.0), z], 1) if np.isfinite(radius) else \
        np.stack([s, np.zeros_like(s), z], 1)
    pts += rng.normal(0, 0.03, pts.shape)
    fit = fit_surface(pts, np.array([0.0, 7.0, 3.0]), FIT, FOOTPRINT_M, toward_camera=np.array([0.0, 1, 0]))
    assert len(set(point_parts(pts, FIT.normal_knn))) == 2
    assert fit.part is None and fit.n_inliers >= 790
    assert fit.surface.radius_m == pytest.approx(radius, rel=0.05)


def plane_continued_by_cylinder(plane_m, arc_m, turn_deg, radius=9.0, noise=0.03, density=25.0, height=6.0,
                                seed=6):
    """Points on a plane y = 0 over x in [-``plane_m``, 0] continued at x = 0, with no gap and no step, by a
    convex cylinder of ``arc_m`` of arc whose tangent there turns from the plane's by ``turn_deg`` (0: the
    two meet tangentially; else at a kink), and the cylinder's axis point."""
    rng = np.random.default_rng(seed)
    n = int(plane_m * height * density)
    plane = np.stack([rng.uniform(-plane_m, 0.0, n), np.zeros(n), rng.uniform(0, height, n)], 1)
    m = int(arc_m * height * density)
    theta = np.radians(turn_deg)
    phi = theta + rng.uniform(0.0, arc_m / radius, m)
    cyl = np.stack([radius * (np.sin(phi) - np.sin(theta)), radius * (np.cos(phi) - np.cos(theta)),
                    rng.uniform(0, height, m)], 1)
    axis_point = np.array([-radius * np.sin(theta), -radius * np.cos(theta)])
    return np.vstack([plane, cyl]) + rng.normal(0, noise, (n + m, 3)), n, axis_point


@pytest.mark.parametrize("turn_deg", [0.0, 15.0])
@pytest.mark.parametrize("framed", ["cylinder", "plane"])
def test_a_plane_continued_by_a_cylinder_without_a_gap_fits_the_part_it_frames(turn_deg, framed):
    """A curved corner continuing a flat wall, tangentially or at a kink, with no gap or step between them:
    one part of the points, and one surface bent through both fits neither. The view fits the surface it
    frames (the one holding most of the points), its radius and axis those drawn. The cylinder beside the
    framed plane bulges 0.125 m over its 3 m of arc, more than its points' scatter can hide (a shorter arc
    is a plane to them, and planes alone are not split)."""
    plane_m, arc_m = (2.0, 5.5) if framed == "cylinder" else (6.0, 3.0)
    pts, n_plane, axis_point = plane_continued_by_cylinder(plane_m, arc_m, turn_deg)
    eye = np.array([pts[:, 0].mean(), 7.0, 3.0])
    fit = fit_surface(pts, eye, FIT, FOOTPRINT_M, toward_camera=np.array([0.0, 1.0, 0.0]))
    assert len(set(point_parts(pts, FIT.normal_knn))) == 1
    s = fit.surface
    main = np.arange(len(pts)) < n_plane if framed == "plane" else np.arange(len(pts)) >= n_plane
    if framed == "plane":
        assert np.isinf(s.radius_m)
        assert abs(s.normal @ [0, 1, 0]) > np.cos(np.radians(1.0))
    else:
        assert s.radius_m == pytest.approx(9.0, rel=0.05)
        assert abs(s.axis @ [0, 0, 1]) > np.cos(np.radians(1.0))
        centre = s.origin - s.normal / s.curvature_per_m
        assert np.linalg.norm(centre[:2] - axis_point) < 0.05 * 9.0
    # where two surfaces meet tangentially they part by less than the points' scatter near the line: the
    # fitted side ends within a metre of it (6 m high at 25 points a square metre: 150 points)
    assert fit.part is not None and abs(fit.n_inliers - main.sum()) < 150
    assert np.sqrt(np.mean(s.signed_distance(pts[main]) ** 2)) < 0.04


def planes_at_kink(first_m, second_m, kink_deg, noise=0.03, density=25.0, height=6.0, seed=6):
    """Points on a plane y = 0 over x in [-``first_m``, 0] continued at x = 0, with no gap and no step, by a
    plane of ``second_m`` width turned from it by ``kink_deg`` about the vertical line where they meet (> 0:
    away from +y, a building's corner; < 0: toward it, a folded bay), the number of the first plane's
    points, and the second plane's unit normal toward +y."""
    rng = np.random.default_rng(seed)
    n = int(first_m * height * density)
    first = np.stack([rng.uniform(-first_m, 0.0, n), np.zeros(n), rng.uniform(0, height, n)], 1)
    m = int(second_m * height * density)
    theta = np.radians(kink_deg)
    s = rng.uniform(0.0, second_m, m)
    second = np.stack([s * np.cos(theta), -s * np.sin(theta), rng.uniform(0, height, m)], 1)
    return np.vstack([first, second]) + rng.normal(0, noise, (n + m, 3)), n, np.array([np.sin(theta),
                                                                                       np.cos(theta), 0.0])


@pytest.mark.parametrize("curved", [True, False])
@pytest.mark.parametrize("kink_deg", [10.0, 40.0, -40.0])
@pytest.mark.parametrize("framed", ["first", "second"])
def test_two_planes_at_a_kink_fit_the_plane_the_view_frames(framed, kink_deg, curved):
    """A view framing a building's corner or a folded bay: two flat walls meeting at a kink with no gap,
    one part of the points. One plane through both fits neither (a facade declared flat took one 1-8 deg
    off either wall); the view fits the plane it frames (the one holding about two thirds of the points),
    its normal that wall's, its inliers ending near the line where the walls meet."""
    first_m, second_m = (5.5, 3.0) if framed == "first" else (3.0, 5.5)
    pts, n_first, second_normal = planes_at_kink(first_m, second_m, kink_deg)
    main = np.arange(len(pts)) < n_first if framed == "first" else np.arange(len(pts)) >= n_first
    normal = np.array([0.0, 1.0, 0.0]) if framed == "first" else second_normal
    eye = pts[main].mean(0) + 7.0 * normal
    fit = fit_surface(pts, eye, FIT, FOOTPRINT_M, toward_camera=normal, curved=curved)
    assert len(set(point_parts(pts, FIT.normal_knn))) == 1
    s = fit.surface
    assert np.isinf(s.radius_m)
    assert s.normal @ normal > np.cos(np.radians(1.0))
    # within half a metre of the line where they meet (75 points) the walls part by less than 3 times the
    # points' scatter at 10 degrees
    assert fit.part is not None and abs(fit.n_inliers - main.sum()) < 75
    assert np.sqrt(np.mean(s.signed_distance(pts[main]) ** 2)) < 0.04


@pytest.mark.parametrize("curved", [True, False])
@pytest.mark.parametrize("kink_deg", [-20.0, 20.0])
@pytest.mark.parametrize("framed", ["first", "second"])
def test_two_planes_at_a_kink_half_and_half_fit_the_plane_the_view_looks_at(framed, kink_deg, curved):
    """A view centred on one of two walls at a kink that hold as many points each (the corner framed half
    and half): neither side holds most, and the view's photo is of the wall its optical axis meets; the fit
    takes that wall's normal, not the other's."""
    pts, n_first, second_normal = planes_at_kink(4.25, 4.25, kink_deg)
    main = np.arange(len(pts)) < n_first if framed == "first" else np.arange(len(pts)) >= n_first
    normal = np.array([0.0, 1.0, 0.0]) if framed == "first" else second_normal
    eye = pts[main].mean(0) + 7.0 * normal
    fit = fit_surface(pts, eye, FIT, FOOTPRINT_M, toward_camera=normal, curved=curved)
    assert np.isinf(fit.surface.radius_m)
    assert fit.surface.normal @ normal > np.cos(np.radians(1.0))
    assert fit.part is not None and abs(fit.n_inliers - main.sum()) < 75


@pytest.mark.parametrize(("radius", "curved"), [(np.inf, True), (np.inf, False), (9.0, True)])
def test_one_surface_with_the_coarse_points_scatter_is_not_split(radius, curved):
    """A single plane (fitted as a plane or a cylinder) or a single cylinder whose points scatter as the
    coarse cloud's (3 cm) is one surface: no split of it into two fits the other side better than the
    whole surface does."""
    rng = np.random.default_rng(8)
    s, z = rng.uniform(-4.0, 4.0, 1200), rng.uniform(0.0, 6.0, 1200)
    phi = s / radius
    pts = np.stack([radius * np.sin(phi), radius * (np.cos(phi) - 1.0), z], 1) if np.isfinite(radius) else \
        np.stack([s, np.zeros_like(s), z], 1)
    pts += rng.normal(0, 0.03, pts.shape)
    fit = fit_surface(pts, np.array([0.0, 7.0, 3.0]), FIT, FOOTPRINT_M, toward_camera=np.array([0.0, 1, 0]),
                      curved=curved)
    assert fit.part is None and fit.n_inliers >= 0.99 * len(pts)
    assert fit.surface.radius_m == pytest.approx(radius, rel=0.05)
