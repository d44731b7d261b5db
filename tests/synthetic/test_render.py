"""Rendering: Schlick's Fresnel (Eq. 8), the deferred shading of Eq. 7 on glass, and mirror geometry."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import open3d as o3d
import pytest

from facade_pipeline.geometry.camera import PinholeCamera, look_at
from facade_pipeline.synthetic.cameras import camera_matrix
from facade_pipeline.synthetic.environment import box_mesh
from facade_pipeline.synthetic.mesh import Material, concat
from facade_pipeline.synthetic.render import SceneArrays, Tracer, first_hits, render_view, schlick, shade
from facade_pipeline.synthetic.scene import build_scene
from tests.synthetic.conftest import replace_in, tiny, without


def test_schlick_grows_toward_grazing_angles():
    f0 = np.array([0.04, 0.5, 0.9])
    cos = np.linspace(1.0, 0.0, 91)
    F = schlick(f0, cos)
    assert F.shape == (91, 3)
    assert np.allclose(F[0], f0) and np.allclose(F[-1], 1.0)
    assert np.all(np.diff(F, axis=0) >= 0) and np.all(F[45] > f0)


def _uniform_sky_scene(fresnel: bool):
    p = tiny()
    p = replace_in(
        p,
        "environment",
        sky_zenith_color=(0.5, 0.6, 0.7),
        sky_horizon_color=(0.5, 0.6, 0.7),
        sun_disc_deg=0.001,
    )
    p = replace_in(p, "facade", interior_color=(0.0, 0.0, 0.0))
    p = without(p, "near_field_reflection")  # R = sky(w_r): here a constant
    if not fresnel:
        p = without(p, "fresnel")
    return build_scene(p)


@pytest.mark.parametrize("fresnel", [True, False])
def test_glass_radiance_is_eq_7_with_schlick_fresnel(fresnel):
    scene = _uniform_sky_scene(fresnel)
    tracer = Tracer(scene.mesh)
    panel = scene.panels[len(scene.panels) // 2]
    X, n = panel.corners.mean(axis=0), panel.normal
    t = np.cross([0.0, 0.0, 1.0], n)
    angles = np.radians([0.0, 30.0, 60.0, 75.0, 80.0])  # at 85 deg a mullion hides the panel centre
    # eyes below X so that reflected rays go up into the (uniform) sky
    eyes = np.array([X + 4.0 * (np.cos(a) * n + np.sin(a) * t) - [0.0, 0.0, 0.3] for a in angles])
    d = (X - eyes) / np.linalg.norm(X - eyes, axis=1, keepdims=True)
    I = shade(scene, tracer, SceneArrays.of(scene), eyes, d)
    cos = -(d @ n)
    f0 = np.asarray(scene.params.facade.glass_f0)
    F = schlick(f0, cos) if fresnel else np.broadcast_to(f0, (len(cos), 3))
    expected = scene.params.facade.glass_reflectivity * F * np.array([0.5, 0.6, 0.7])
    assert np.allclose(I, expected, rtol=1e-6)
    assert tracer.counts.secondary == 0
    if fresnel:
        assert np.all(np.diff(I, axis=0) > 0)  # brighter toward grazing
    else:
        assert np.allclose(I, I[0])


@pytest.fixture(scope="module")
def mirror_setup():
    """A planar facade, a red box 5 m in front of a panel and 2 m to its right, and a camera placed where
    mirror geometry makes the box's reflection appear at the panel's centre M."""
    p = tiny()
    grey = (0.5, 0.5, 0.5)
    p = replace_in(
        p,
        "environment",
        building_colors=(grey,),
        trunk_color=grey,
        crown_color=grey,
        court_color=grey,
        grass_color=grey,
        water_color=grey,
    )
    p = replace_in(p, "facade", wall_color=(1.0, 0.0, 0.0))  # the box is made of the body-wall material,
    # which the glass cannot reflect (the body lies behind the glass plane)
    p = replace_in(p, "render", supersample=1)
    scene = build_scene(p)
    panel = scene.panels[1 * p.parts[0].cols + 1]
    M, n = panel.corners.mean(axis=0), panel.normal
    t = np.cross([0.0, 0.0, 1.0], n)
    B = M + 5.0 * n + 2.0 * t
    box = box_mesh(B - [0, 0, 0.5], np.array([1.0, 1.0, 1.0]), 0.0, Material.WALL)
    scene = dataclasses.replace(
        scene, environment=concat([scene.environment, box]), mesh=concat([scene.mesh, box])
    )
    B_mirror = B - 2.0 * ((B - M) @ n) * n
    eye = M + 1.6 * (M - B_mirror)
    cam = PinholeCamera(camera_matrix(64, 64, 40.0), look_at(eye, M), 64, 64)
    mirrored_box = box_mesh(B_mirror - [0, 0, 0.5], np.array([1.0, 1.0, 1.0]), 0.0, Material.WALL)
    return scene, cam, M, n, mirrored_box


def _cast(mesh, o, d):
    rc = o3d.t.geometry.RaycastingScene()
    rc.add_triangles(
        o3d.core.Tensor(mesh.vertices.astype(np.float32)), o3d.core.Tensor(mesh.triangles.astype(np.uint32))
    )
    return rc.cast_rays(o3d.core.Tensor(np.concatenate([o, d], 1).astype(np.float32)))["t_hit"].numpy()


def test_reflected_ray_hits_the_object_where_mirror_geometry_puts_it(mirror_setup):
    scene, cam, M, n, mirrored_box = mirror_setup
    tracer, arrays = Tracer(scene.mesh), SceneArrays.of(scene)
    o = cam.center[None]
    d = (M - cam.center)[None] / np.linalg.norm(M - cam.center)
    h = first_hits(tracer, arrays, o, d, "other")
    assert h.material[0] == Material.GLASS and np.linalg.norm(h.points[0] - M) < 1e-4
    w_r = d - 2.0 * (d @ h.normals[0])[:, None] * h.normals[0]
    h2 = first_hits(tracer, arrays, h.points + 1e-3 * h.normals, w_r, "other")
    t_virtual = _cast(mirrored_box, o, d)[0]  # the straight ray meets the mirror image of the box
    Q_virtual = o[0] + t_virtual * d[0]
    Q = Q_virtual - 2.0 * ((Q_virtual - M) @ n) * n
    assert h2.material[0] == Material.WALL and h2.prim[0] >= len(scene.mesh.triangles) - 12
    assert np.linalg.norm(h2.points[0] - Q) < 1e-3


def test_reflection_of_the_object_appears_exactly_where_predicted(mirror_setup):
    scene, cam, M, n, mirrored_box = mirror_setup
    tracer, arrays = Tracer(scene.mesh), SceneArrays.of(scene)
    r = render_view(scene, tracer, arrays, cam)
    o, d = cam.all_pixel_rays(1)
    predicted = np.isfinite(_cast(mirrored_box, o, d)).reshape(64, 64) & (r.material == Material.GLASS)
    redness = r.image[..., 0] - r.image[..., 1:].max(axis=-1)
    red = (redness > 0.1) & (r.material == Material.GLASS)
    assert predicted.sum() > 20
    kernel = np.ones((3, 3), np.uint8)
    core = cv2.erode(predicted.astype(np.uint8), kernel).astype(bool)
    halo = cv2.dilate(predicted.astype(np.uint8), kernel).astype(bool)
    assert np.all(red[core]) and not np.any(red[~halo])
    scene_off = dataclasses.replace(scene, params=without(scene.params, "near_field_reflection"))
    r_off = render_view(scene_off, Tracer(scene.mesh), arrays, cam)
    assert not np.any((r_off.image[..., 0] - r_off.image[..., 1:].max(axis=-1) > 0.1) & (r.material == 1))


def test_reflections_move_with_parallax(mirror_setup):
    """Near-field: the box's reflection shifts on the glass when the camera moves sideways, by the amount
    mirror geometry predicts (an environment map at infinity would not move it)."""
    scene, cam, M, n, mirrored_box = mirror_setup
    tracer, arrays = Tracer(scene.mesh), SceneArrays.of(scene)
    t = np.cross([0.0, 0.0, 1.0], n)
    for shift in (-1.0, 1.0):
        eye = cam.center + shift * t
        cam2 = PinholeCamera(cam.K, look_at(eye, M), 64, 64)
        r = render_view(scene, tracer, arrays, cam2)
        o, d = cam2.all_pixel_rays(1)
        predicted = np.isfinite(_cast(mirrored_box, o, d)).reshape(64, 64) & (r.material == Material.GLASS)
        red = (r.image[..., 0] - r.image[..., 1:].max(axis=-1) > 0.1) & (r.material == Material.GLASS)
        ys, xs = np.nonzero(red)
        py, px = np.nonzero(predicted)
        assert len(xs) > 10 and abs(xs.mean() - px.mean()) < 1.0 and abs(ys.mean() - py.mean()) < 1.0
