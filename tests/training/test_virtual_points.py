"""The reflections' virtual points (``shading.surroundings.unmirror``): on a glass plane of known pose, the
points photogrammetry finds behind the glass for the surroundings' reflections go back to where the
surroundings stand; roofs seen over the facade, points no photo sees, the facade's own points and the
surroundings in front stay where they are; a glass that is no plane mirrors nothing."""

from __future__ import annotations

import math

import numpy as np
import torch

from facade_pipeline.geometry.camera import PinholeCamera
from facade_pipeline.shading.surroundings import (
    Surroundings,
    glass_plane,
    mirrored,
    surroundings_points,
    unmirror,
)

#: the facade's frame in the world: s along it, up, n its normal towards the cameras (turned 30 deg about z)
YAW = math.radians(30.0)
S_AXIS = np.array([math.cos(YAW), math.sin(YAW), 0.0])
N_AXIS = np.array([-math.sin(YAW), math.cos(YAW), 0.0])
UP = np.array([0.0, 0.0, 1.0])
ORIGIN = np.array([3.0, -2.0, 0.0])
#: the glass: s in [-5, 5] m, heights [0, 10] m
WIDTH, HEIGHT = 10.0, 10.0
MARGIN = 0.2


def _world(s, z, n) -> np.ndarray:
    """[N, 3] world points at facade coordinates (s, height, distance in front of the glass)."""
    s, z, n = np.broadcast_arrays(*(np.asarray(a, np.float64) for a in (s, z, n)))
    return ORIGIN + s[:, None] * S_AXIS + z[:, None] * UP + n[:, None] * N_AXIS


def _glass_mesh(bulge: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The glass as a 4 x 4 grid of cells (triangles alternately wound) and a frame strip beside it that is
    not glass; ``bulge``: the glass bent out of its plane by this much at its middle (m)."""
    s, z = np.meshgrid(np.linspace(-WIDTH / 2, WIDTH / 2, 5), np.linspace(0.0, HEIGHT, 5))
    n = bulge * np.cos(math.pi * s / WIDTH)
    verts = _world(s.ravel(), z.ravel(), n.ravel())
    idx = np.arange(25).reshape(5, 5)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    tris = np.concatenate([np.stack([a, b, c], 1), np.stack([a, d, c], 1)])
    # a frame 0.3 m in front of the glass, beside it: part of the mesh, not of the mirror
    frame = _world([WIDTH / 2, WIDTH / 2 + 1, WIDTH / 2 + 1, WIDTH / 2], [0, 0, HEIGHT, HEIGHT], 0.3)
    verts = np.concatenate([verts, frame])
    tris = np.concatenate([tris, [[25, 26, 27], [25, 27, 28]]])
    glass = np.r_[np.ones(len(tris) - 2, bool), False, False]
    return verts, tris, glass


def _cameras() -> list[PinholeCamera]:
    """Nine cameras 20 m in front of the glass, at s in [-4, 4] and heights 3-7 m, looking at it."""
    K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
    cams = []
    for s in (-4.0, 0.0, 4.0):
        for z in (3.0, 5.0, 7.0):
            c = _world([s], [z], [20.0])[0]
            R = np.stack([S_AXIS, -UP, -N_AXIS])  # camera x right, y down, z forward (towards the glass)
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = R, -R @ c
            cams.append(PinholeCamera(K, T, 640, 480))
    return cams


def _scene(rng: np.random.Generator):
    """(points, truth, virtual): a survey's points, where each truly stands, and which are virtual."""
    n = 300
    # trees and a building 5-15 m in front: their mirror images lie as far behind, seen through the glass
    real = _world(rng.uniform(-3, 3, n), rng.uniform(2, 8, n), rng.uniform(5, 15, n))
    front = _world(rng.uniform(-8, 8, n), rng.uniform(0, 8, n), rng.uniform(3, 15, n))
    # the roof of the building behind the facade, above the glass: photos see it over the facade
    roof = _world(rng.uniform(-5, 5, n), np.full(n, 12.0), -rng.uniform(1, 10, n))
    # far to the side behind the facade, in no photo
    unseen = _world(rng.uniform(150, 200, 20), rng.uniform(0, 8, 20), -rng.uniform(1, 10, 20))
    # on the glass and just behind it, within the margin (the glass's own points, dust)
    glass = _world(rng.uniform(-5, 5, n), rng.uniform(0, 10, n), rng.uniform(-0.5, 0.1, n) * MARGIN)
    truth = np.concatenate([real, front, roof, unseen, glass])
    points = truth.copy()
    points[:n] = _mirror_by_hand(real)
    virtual = np.zeros(len(points), bool)
    virtual[:n] = True
    return points, truth, virtual


def _mirror_by_hand(p: np.ndarray) -> np.ndarray:
    """Mirror ``p`` through the glass plane in the facade's own coordinates: n -> -n."""
    rel = p - ORIGIN
    s, z, n = rel @ S_AXIS, rel @ UP, rel @ N_AXIS
    return _world(s, z, -n)


def test_the_glass_plane_faces_the_cameras():
    verts, tris, glass = _glass_mesh()
    cams = _cameras()
    plane = glass_plane(verts, tris, glass, np.array([c.center for c in cams]))
    assert plane is not None
    np.testing.assert_allclose(plane.normal, N_AXIS, atol=1e-12)
    np.testing.assert_allclose(plane.signed_distance(ORIGIN[None]), [0.0], atol=1e-9)
    np.testing.assert_allclose(plane.hi - plane.lo, [WIDTH, HEIGHT], atol=1e-9)
    # one pane of two triangles
    pane = _world([-5.0, 5.0, 5.0, -5.0], [0.0, 0.0, 10.0, 10.0], 0.0)
    eyes = np.array([c.center for c in cams])
    one = glass_plane(pane, np.array([[0, 1, 2], [0, 2, 3]]), np.ones(2, bool), eyes)
    np.testing.assert_allclose(one.normal, N_AXIS, atol=1e-12)
    np.testing.assert_allclose(one.hi - one.lo, [WIDTH, HEIGHT], atol=1e-9)
    # seen from behind, the same plane faces the other way
    behind = glass_plane(verts, tris, glass, _world([0.0], [5.0], [-20.0]))
    np.testing.assert_allclose(behind.normal, -N_AXIS, atol=1e-12)


def test_virtual_points_go_back_to_the_surroundings():
    rng = np.random.default_rng(0)
    points, truth, virtual = _scene(rng)
    verts, tris, glass = _glass_mesh()
    cams = _cameras()
    plane = glass_plane(verts, tris, glass, np.array([c.center for c in cams]))
    np.testing.assert_array_equal(unmirror(points, plane, cams, MARGIN), virtual)
    out, n = surroundings_points(points, verts, tris, glass, cams, MARGIN)
    assert n == virtual.sum()
    np.testing.assert_allclose(out, truth, atol=1e-9)
    np.testing.assert_allclose(mirrored(mirrored(points, plane), plane), points, atol=1e-9)


def test_the_surroundings_of_virtual_points_are_those_of_the_real_ones():
    rng = np.random.default_rng(1)
    points, truth, _ = _scene(rng)
    verts, tris, glass = _glass_mesh()
    cams = _cameras()
    out, _ = surroundings_points(points, verts, tris, glass, cams, MARGIN)
    lo, hi = torch.as_tensor(verts.min(0)), torch.as_tensor(verts.max(0))

    def heights(p):
        return Surroundings(lo, hi, reach_m=30.0, cell_m=1.0, points=p, margin_m=MARGIN).heights

    torch.testing.assert_close(heights(out), heights(truth), rtol=0, atol=1e-5)
    # as the survey gives them, the reflections' points stand behind the facade, where no reflected ray goes
    assert not torch.equal(heights(points), heights(truth))


def test_no_glass_or_a_curved_one_mirrors_nothing():
    rng = np.random.default_rng(2)
    points, _, _ = _scene(rng)
    cams = _cameras()
    verts, tris, glass = _glass_mesh()
    out, n = surroundings_points(points, verts, tris, None, cams, MARGIN)
    assert n == 0 and out is points
    out, n = surroundings_points(points, verts, tris, np.zeros_like(glass), cams, MARGIN)
    assert n == 0
    verts, tris, glass = _glass_mesh(bulge=1.0)  # 1 m out of plane over 10 m: a curved wall
    assert glass_plane(verts, tris, glass, np.array([c.center for c in cams])) is None
    out, n = surroundings_points(points, verts, tris, glass, cams, MARGIN)
    assert n == 0
