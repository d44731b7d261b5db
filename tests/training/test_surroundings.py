"""The environment proxy's surroundings (``shading.surroundings``): the surface model made from points, its
holes, its blocks, rays cast against it worked out by hand, hard rays, the saved state, and a short training
run."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from facade_pipeline.shading.reflection import EnvironmentProxy, ReflectionMLP, build_reflection_module
from facade_pipeline.shading.surroundings import Surroundings, surface_heights, surface_mesh

LO = torch.tensor([-5.0, -1.0, 0.0])
HI = torch.tensor([5.0, 1.0, 10.0])
#: a block of a building in front of the facade: x in [-10, 10], y in [20, 30], 8 m high
BLOCK = ((-10.0, 20.0), (10.0, 30.0), 8.0)


def _points(rng: np.random.Generator, roof_hole: bool = False) -> np.ndarray:
    """Points on BLOCK's walls and roof, ground points (z < 0.3 m) all around, facade points inside the
    bounds. ``roof_hole``: none on the roof around (0.5, 25.5)."""
    (x0, y0), (x1, y1), h = BLOCK
    roof = np.column_stack([rng.uniform(x0, x1, 3000), rng.uniform(y0, y1, 3000), np.full(3000, h)])
    if roof_hole:
        roof = roof[~((np.abs(roof[:, 0] - 0.5) < 0.5) & (np.abs(roof[:, 1] - 25.5) < 0.5))]
    front = np.column_stack([rng.uniform(x0, x1, 1000), np.full(1000, y0), rng.uniform(0, h, 1000)])
    ground = np.column_stack([rng.uniform(-60, 60, (5000, 2)), rng.uniform(0, 0.3, 5000)])
    facade = rng.uniform(LO.numpy(), HI.numpy(), (2000, 3))
    return np.concatenate([roof, front, ground, facade])


def _surroundings(points: np.ndarray | None) -> Surroundings:
    return Surroundings(LO, HI, reach_m=40.0, cell_m=1.0, points=points, margin_m=1.0)


def _cell(x: float, y: float, n: int = 80) -> tuple[int, int]:
    """The cell of (x, y) in an 80 x 80 grid of 1 m cells centred on the facade's centre (0, 0)."""
    return int(np.floor(x + n / 2)), int(np.floor(y + n / 2))


def test_surface_heights_of_a_block_of_points():
    rng = np.random.default_rng(0)
    bottom, top = surface_heights(_points(rng), LO.numpy(), HI.numpy(), 80, 1.0, 1.0)
    assert top.shape == (80, 80)
    (x0, y0), (x1, y1), h = BLOCK
    rows = slice(_cell(x0 + 1, 0)[0], _cell(x1 - 1, 0)[0] + 1)
    np.testing.assert_allclose(top[rows, _cell(0, y0 + 1)[1] : _cell(0, y1 - 1)[1] + 1], h)
    # the front wall's points reach down to the ground; behind it only the roof's: a slab, hidden by the wall
    assert (bottom[rows, _cell(0, y0)[1]] == 0).all()
    assert (bottom[rows, _cell(0, 25)[1]] == h).all()
    # the ground, the facade's own points and everything else: nothing
    outside = np.ones_like(top, bool)
    outside[_cell(x0, 0)[0] : _cell(x1, 0)[0] + 1, _cell(0, y0)[1] : _cell(0, y1)[1] + 1] = False
    assert (top[outside] == 0).all() and (bottom[outside] == 0).all()


def test_a_hole_in_a_roof_is_filled():
    points = _points(np.random.default_rng(1), roof_hole=True)
    bottom, top = surface_heights(points, LO.numpy(), HI.numpy(), 80, 1.0, 1.0)
    assert top[_cell(0.5, 25.5)] == BLOCK[2] and bottom[_cell(0.5, 25.5)] == BLOCK[2]


def _quads(heights: np.ndarray) -> np.ndarray:
    v, f = surface_mesh(heights, 2.0, np.array([0.0, 0.0]), -1.0)
    assert len(f) % 2 == 0
    return v.reshape(-1, 4, 3)


def test_surface_mesh_of_blocks():
    heights = np.zeros((2, 4, 4))
    heights[1, 1, 2] = 3.0  # one block on the ground
    q = _quads(heights)
    assert len(q) == 5  # its top and four walls
    v = q.reshape(-1, 3)
    assert v[:, 0].min() == -2.0 and v[:, 0].max() == 0.0  # row 1 spans x in [-2, 0]
    assert v[:, 1].min() == 0.0 and v[:, 1].max() == 2.0  # column 2 spans y in [0, 2]
    assert v[:, 2].min() == -1.0 and v[:, 2].max() == 2.0
    heights[0, 1, 2] = 2.0  # the same block lifted off the ground: a bottom too, walls 1 m high
    q = _quads(heights)
    assert len(q) == 6 and q[:, :, 2].min() == 1.0
    # a lower, shorter block beside a full one: the full one's wall toward it shows above and below it
    heights[:] = 0.0
    heights[1, 1, 1], heights[:, 1, 2] = 3.0, [1.0, 2.0]
    q = _quads(heights)
    shared = q[np.all(q[:, :, 1] == 0.0, axis=1)]  # quads in the plane y = 0 between the two columns
    spans = sorted((float(a.min()), float(a.max())) for a in shared[:, :, 2])
    assert spans == [(-1.0, 0.0), (1.0, 2.0)]


def test_rays_worked_by_hand():
    s = _surroundings(_points(np.random.default_rng(2)))
    top = s.top
    # the block's top front edge seen from the eye (0, 0, 0): 8 m up, 20 m out
    assert top == pytest.approx(math.atan2(8.0, 20.0 - 0.71), abs=0.02)
    x = torch.tensor([[0.0, 0.0, 5.0]] * 4)
    w = torch.nn.functional.normalize(
        torch.tensor(
            [
                [0.0, 1.0, 0.0],  # straight out, level: the block's front wall at (0, 20, 5)
                [0.0, 1.0, -0.5],  # down: the ground at (0, 10)
                [0.0, 1.0, 0.5],  # up, over the block: the sky
                [0.0, -1.0, 0.0],  # behind the facade: nothing there, the sky at the horizon
            ]
        ),
        dim=1,
    )
    on_floor, floor_uv, wall_uv = s.hit(x, w)
    assert on_floor.tolist() == [False, True, False, False]
    # the wall: azimuth 90 deg, elevation atan(5 / 20) from the eye, in the lower half over the top
    assert wall_uv[0].tolist() == pytest.approx([0.5, -1.0 + math.atan2(5.0, 20.0) / top], abs=1e-4)
    assert floor_uv[1].tolist() == pytest.approx([0.0, 10.0 / 40.0], abs=1e-4)
    # the sky by the direction: azimuth 90 deg, elevation asin(0.5 / sqrt 1.25) over 90 deg
    sky_v = math.asin(0.5 / math.sqrt(1.25)) / (math.pi / 2)
    assert wall_uv[2].tolist() == pytest.approx([0.5, sky_v], abs=1e-5)
    assert wall_uv[3].tolist() == pytest.approx([-0.5, 0.0], abs=1e-5)


def test_a_ray_passes_under_a_crown():
    # a crown of points 4-7 m up over (0, 15) +- 2 m, nothing under it: a ray from 1 m up the facade reaches
    # the ground behind it; one at 5 m meets it
    rng = np.random.default_rng(5)
    crown = np.column_stack([rng.uniform(-2, 2, 4000), rng.uniform(13, 17, 4000), rng.uniform(4, 7, 4000)])
    s = _surroundings(crown)
    x = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 5.0]])
    w = torch.nn.functional.normalize(torch.tensor([[0.0, 1.0, -0.05], [0.0, 1.0, 0.0]]), dim=1)
    on_floor, floor_uv, wall_uv = s.hit(x, w)
    assert on_floor.tolist() == [True, False]
    assert floor_uv[0, 1].item() == pytest.approx(20.0 / 40.0, abs=1e-3)
    assert wall_uv[1, 1].item() < 0.0  # the crown, in the lower half


def test_hard_rays_are_finite():
    s = _surroundings(_points(np.random.default_rng(3)))
    nan = float("nan")
    x = torch.tensor([[0.0, 0.0, 5.0], [nan, 0.0, 1.0], [0.0, 0.0, -3.0], [1e6, 1e6, 1e6], [0, 0, 0]])
    w = torch.tensor([[0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [0.0, 0.0, 1.0], [0, 0, 1.0]])
    for out in s.hit(x, w)[1:]:
        assert torch.isfinite(out).all() and out.abs().max() <= 1.0
    # no points at all: only the ground and the sky
    empty = _surroundings(np.zeros((0, 3)))
    on_floor, _, wall_uv = empty.hit(x[:1], torch.tensor([[0.0, 1.0, 0.0]]))
    assert not on_floor[0] and wall_uv[0, 1].item() == 0.0


@pytest.mark.parametrize(("reach", "cell"), [(0.0, 1.0), (40.0, 0.0), (40.0, -1.0), (1e5, 1.0)])
def test_bad_sizes_are_refused(reach, cell):
    with pytest.raises(ValueError, match="surroundings"):
        Surroundings(LO, HI, reach_m=reach, cell_m=cell)


def test_saved_state_casts_against_the_same_surface():
    cfg = ReflectionMLP(2, 2, 8, True, EnvironmentProxy(channels=2, resolution_px=16, levels=1))
    points = _points(np.random.default_rng(4))
    torch.manual_seed(0)
    m = build_reflection_module(cfg, "cpu", (LO, HI), points=points)
    assert "proxy.surroundings.heights" in m.state_dict()
    assert not any(n.startswith("proxy.surroundings") for n, _ in m.named_parameters())
    loaded = build_reflection_module(cfg, "cpu", (LO, HI))  # no points: empty until the state is loaded
    assert not loaded.proxy.surroundings.heights.any()  # ground only
    x = torch.tensor([[0.0, 0.0, 5.0], [1.0, 0.0, 2.0]])
    w = torch.nn.functional.normalize(torch.tensor([[0.0, 1.0, 0.1], [0.3, 1.0, -0.02]]), dim=1)
    loaded.proxy(x, w)  # builds the empty surface's ray caster before the state arrives
    loaded.load_state_dict(m.state_dict())
    xn = 2 * (x - LO) / (HI - LO) - 1
    assert torch.equal(loaded(xn, w), m(xn, w))
    assert torch.equal(loaded.proxy(x, w), m.proxy(x, w))


def test_training_with_surroundings_saves_and_renders_back(data64, tmp_path):
    """A short run on synthetic64 with the surroundings: some reflected rays meet them, everything stays
    finite, and the saved model renders what the trainer renders."""
    from facade_pipeline.config import to_dict
    from facade_pipeline.evaluation.render_views import (
        from_trainer,
        load_trained,
        render_trained,
    )
    from facade_pipeline.training.render import splatting_rasterizer
    from facade_pipeline.training.trained import TrainedModelFiles
    from facade_pipeline.training.trainer import build_trainer, train
    from tests.training.conftest import small_params

    p = small_params(iterations=6, proxy_channels=2)
    tr = build_trainer(p, data64, splatting_rasterizer("torch"))
    sur = tr.state.reflection.proxy.surroundings
    assert sur.heights[1].max() > 1.0  # synthetic64's coarse points hold trees and buildings
    seen = []
    hit = sur.hit
    sur.hit = lambda x, w: seen.append(out := hit(x, w)) or out
    train(tr)
    del sur.hit
    on_floor = torch.cat([o[0] for o in seen])
    on_wall = torch.cat([o[2][:, 1] < 0 for o in seen]) & ~on_floor
    assert on_floor.numel() > 0 and bool(on_wall.any())
    assert all(torch.isfinite(q).all() for q in tr.state.reflection.parameters())
    split = {"train": [], "test": []}
    files = TrainedModelFiles.variant(tmp_path, to_dict(p))
    strategy = p.reflection_strategy(data64.bounds)
    files.save(tr.state.model, tr.state.reflection, strategy, data64.bounds, split)
    loaded = load_trained(TrainedModelFiles.from_dir(tmp_path))
    assert torch.equal(loaded.reflection.proxy.surroundings.heights, sur.heights)
    v = data64.views[data64.test_idx[0]]
    a = render_trained(loaded, v.camera, v.facade_mask)
    b = render_trained(from_trainer(tr, "live"), v.camera, v.facade_mask)
    np.testing.assert_allclose(a.rgb, b.rgb, atol=1e-5)


def _random_blocks(seed: int, n: int = 40) -> Surroundings:
    """Surroundings of 40 x 40 cells of 1 m with random blocks: a third of the cells, 1-15 m high, half of
    them standing on the ground, the others lifted (crowns); loaded as a saved state is."""
    rng = np.random.default_rng(seed)
    top = np.where(rng.random((n, n)) < 0.33, rng.uniform(1.0, 15.0, (n, n)), 0.0)
    lifted = rng.random((n, n)) < 0.5
    bottom = np.where(lifted & (top > 0), rng.uniform(0.2, 0.9, (n, n)) * top, 0.0)
    s = Surroundings(LO, HI, reach_m=n / 2, cell_m=1.0)
    s.load_state_dict({"heights": torch.as_tensor(np.stack([bottom, top]), dtype=torch.float32)})
    return s


def _rays(kind: str, s: Surroundings, rng: np.random.Generator, n: int = 4000):
    o = np.column_stack([rng.uniform(-22, 22, (n, 2)), rng.uniform(0.05, 18, n)])
    d = rng.normal(size=(n, 3))
    if kind == "grazing":
        # nearly level (skimming the blocks' tops and bottoms) or nearly along x or y (their walls)
        third = n // 3
        d[:third, 2] = rng.normal(0, 1e-3, third)
        d[third : 2 * third, 1] = rng.normal(0, 1e-3, third)
        d[2 * third :, 0] = rng.normal(0, 1e-3, n - 2 * third)
    if kind == "inside":
        bottom, top = s.heights.double().numpy()
        i, j = np.nonzero(top > 0)
        pick = rng.integers(0, len(i), n)
        f = rng.uniform(0.05, 0.95, (n, 3))
        corner = np.array(s.eye_xy) - 0.5 * top.shape[0]
        o[:, :2] = corner + np.column_stack([i[pick], j[pick]]) + f[:, :2]
        o[:, 2] = s.ground_z + bottom[i[pick], j[pick]] + f[:, 2] * (top - bottom)[i[pick], j[pick]]
    return o, d / np.linalg.norm(d, axis=1, keepdims=True)


def _kind(o: np.ndarray, d: np.ndarray, t: np.ndarray, ground_z: float) -> np.ndarray:
    """0: the ray meets the floor first, 1: a block, 2: neither (the sky), as ``Surroundings.hit`` decides."""
    down = d[:, 2] < -1e-6
    t_floor = np.where(down, np.maximum(o[:, 2] - ground_z, 0) / np.where(down, -d[:, 2], 1), np.inf)
    floor = down & (t_floor < t)
    return np.where(floor, 0, np.where(np.isfinite(t), 1, 2))


@pytest.mark.parametrize("kind", ["random", "grazing", "inside"])
def test_torch_cast_matches_open3d_on_the_blocks_mesh(kind):
    """The cast in torch (a GPU's) against open3d's cast against the blocks as triangles (``surface_mesh``,
    the CPU's): the same rays hit, within 1e-4 m, and the rays meet the floor, a block or the sky alike."""
    pytest.importorskip("open3d")
    from facade_pipeline.geometry.raycast import MeshRaycaster

    s = _random_blocks(7)
    rng = np.random.default_rng({"random": 0, "grazing": 1, "inside": 2}[kind])
    o, d = _rays(kind, s, rng)
    hits = MeshRaycaster(*s.mesh()).cast(o, d)
    ref = hits.t.astype(np.float64)
    o32, d32 = (torch.as_tensor(a, dtype=torch.float32) for a in (o, d))
    got = s.cast_torch(o32, d32).numpy()
    if kind == "inside":
        assert np.isfinite(ref).mean() > 0.5  # most leave through a face (the rest through the ground)
    assert (np.isfinite(ref) == np.isfinite(got)).all()
    hit = np.isfinite(ref)
    # both casts are float32: the ray's position is rounded to a few micrometres at these coordinates, which
    # moves a hit along the ray by that over the cosine at which the ray meets the face (a ray nearly along
    # a wall); 1e-4 m beyond that
    cos = np.abs((d * hits.normal).sum(1))[hit]
    assert hit.any() and (np.abs(got[hit] - ref[hit]) <= 1e-4 + 4e-6 / np.maximum(cos, 1e-9)).all()
    assert (_kind(o, d, got, s.ground_z) == _kind(o, d, ref, s.ground_z)).all()
