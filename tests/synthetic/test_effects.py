"""Only declared effects are simulated, and switching one off changes nothing but that effect."""

from __future__ import annotations

import numpy as np
import pytest

from facade_pipeline.io.images import to_uint8
from facade_pipeline.synthetic.coarse import coarse_mesh, coarse_points, frame_flags
from facade_pipeline.synthetic.mesh import Material
from facade_pipeline.synthetic.render import render_view
from facade_pipeline.synthetic.simulate import build_simulator, raw_camera, sensor_image
from tests.synthetic.conftest import replace_in, tiny, with_effects, without


def _renders(p):
    sim = build_simulator(p)
    views = sim.views[:2] + sim.views[-1:]
    return sim, [render_view(sim.scene, sim.tracer, sim.arrays, v.camera) for v in views]


@pytest.mark.parametrize("effect", ["near_field_reflection", "fresnel"])
def test_glass_effects_change_glass_pixels_only(effect):
    p = replace_in(tiny(), "render", supersample=1)  # one ray per pixel: a pixel is glass or it is not
    on_sim, on = _renders(p)
    off_sim, off = _renders(without(p, effect))
    change = 0.0
    for a, b in zip(on, off, strict=True):
        glass = a.material == Material.GLASS
        for k in ("normals", "depth", "valid", "reflectivity", "material"):
            assert np.array_equal(getattr(a, k), getattr(b, k)), k
        assert np.array_equal(a.image[~glass], b.image[~glass])
        change = max(change, np.abs(a.image[glass] - b.image[glass]).max())
    assert change > 1e-3  # with F0 about 0.5 Fresnel changes little away from grazing angles
    assert on_sim.tracer.counts.primary == off_sim.tracer.counts.primary
    if effect == "near_field_reflection":
        assert on_sim.tracer.counts.secondary > 0 and off_sim.tracer.counts.secondary == 0
    else:
        assert on_sim.tracer.counts.secondary == off_sim.tracer.counts.secondary


def test_secondary_rays_are_cast_for_glass_hits_only():
    p = replace_in(tiny(), "render", supersample=1)
    sim, renders = _renders(p)
    glass_pixels = sum(int((r.material == Material.GLASS).sum()) for r in renders)
    assert sim.tracer.counts.secondary == glass_pixels  # one bounce per glass hit, nothing else


def test_without_sensor_effects_raw_images_equal_clean_images():
    p = tiny()
    assert "exposure_change" not in p.effects
    sim, renders = _renders(without(p, "sensor_noise"))
    for view, r in zip(sim.views[:2] + sim.views[-1:], renders, strict=True):
        assert np.array_equal(sensor_image(sim.scene.params, view, r.image), to_uint8(np.clip(r.image, 0, 1)))


def test_sensor_noise_and_exposure_have_the_declared_amounts():
    p = replace_in(with_effects(tiny(), "exposure_change"), "noise", sensor_std=0.02, exposure_stops=0.5)
    sim = build_simulator(p)
    image = np.full((64, 64, 3), 0.5, np.float32)
    gains = []
    for view in sim.views:
        noisy = sensor_image(p, view, image).astype(float) / 255
        only_exposure = sensor_image(without(p, "sensor_noise"), view, image).astype(float) / 255
        assert 0.015 < np.std(noisy - only_exposure) < 0.025
        gains.append(only_exposure.mean() / 0.5)
    assert all(2**-0.5 - 0.01 <= g <= 2**0.5 + 0.01 for g in gains) and np.ptp(gains) > 0.05
    only_noise = sensor_image(without(p, "exposure_change"), sim.views[0], image)
    assert abs(only_noise.astype(float).mean() / 255 - 0.5) < 0.01


def test_pose_noise_moves_raw_poses_only():
    p = replace_in(with_effects(tiny(), "pose_noise"), "noise", pose_rotation_deg=0.5, pose_translation_m=0.1)
    sim_on, sim_off = build_simulator(p), build_simulator(without(p, "pose_noise"))
    offsets, angles = [], []
    for a, b in zip(sim_on.views, sim_off.views, strict=True):
        assert np.array_equal(a.camera.cam_from_world, b.camera.cam_from_world)  # true poses unchanged
        assert raw_camera(without(p, "pose_noise"), a) is a.camera
        noisy = raw_camera(p, a)
        offsets.append(noisy.center - a.camera.center)
        R = noisy.cam_from_world[:3, :3] @ a.camera.cam_from_world[:3, :3].T
        angles.append(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))
    assert 0.02 < np.std(offsets) < 0.3 and 0.0 < np.max(angles) < 2.5


def test_coarse_effects_change_only_the_coarse_outputs():
    p = tiny()
    on, off = build_simulator(p), build_simulator(without(p, "coarse_mesh_distortion"))
    for a, b in zip(on.views, off.views, strict=True):
        assert np.array_equal(a.camera.cam_from_world, b.camera.cam_from_world)
    assert np.array_equal(on.scene.mesh.vertices, off.scene.mesh.vertices)
    m_on, _ = coarse_mesh(on.scene)
    m_off, _ = coarse_mesh(off.scene)
    assert len(m_on.triangles) < len(m_off.triangles)  # holes
    g = off.scene.parts[0]
    facade = m_off.vertices[np.unique(m_off.triangles[m_off.material != Material.WALL])]  # not the roofs
    s, z, h = g.surface_coords(facade)
    assert np.allclose(h, np.where(frame_flags(g, s, z), p.facade.frame_depth_m, 0.0), atol=1e-9)
    pts_on, pts_off = coarse_points(on.scene), coarse_points(off.scene)  # the point cloud is another effect
    assert np.array_equal(pts_on[0], pts_off[0]) and np.array_equal(pts_on[1], pts_off[1])


def test_glass_point_artifacts_off_gives_full_glass_and_no_ghosts():
    p = tiny()
    on, off = (
        coarse_points(build_simulator(p).scene),
        coarse_points(build_simulator(without(p, "coarse_points_glass_artifacts")).scene),
    )
    g = build_simulator(p).scene.parts[0]
    n_env = p.coarse.environment_points
    assert np.array_equal(on[0][-n_env:], off[0][-n_env:])  # environment points untouched
    for xyz, ghosts_expected in ((on[0][:-n_env], True), (off[0][:-n_env], False)):
        s, z, h = g.surface_coords(xyz)
        behind = h < -1e-6
        assert behind.any() == ghosts_expected
    s_on, z_on, h_on = g.surface_coords(on[0][:-n_env])
    s_off, z_off, h_off = g.surface_coords(off[0][:-n_env])
    glass_on = (np.abs(h_on) < 1e-6) & ~frame_flags(g, s_on, z_on)
    glass_off = (np.abs(h_off) < 1e-6) & ~frame_flags(g, s_off, z_off)
    ratio = glass_on.sum() / glass_off.sum()
    assert abs(ratio - p.coarse.glass_points_keep_fraction) < 0.05
    frames_on = frame_flags(g, s_on, z_on) & (h_on > 0)
    assert frames_on.sum() == (frame_flags(g, s_off, z_off) & (h_off > 0)).sum()
