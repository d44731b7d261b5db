"""Gaussian model, initialisation, densification bookkeeping and the PLY export."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from facade_pipeline.training.data import InitGeometry, split_views
from facade_pipeline.training.densify import (
    DensifyStats,
    densify_and_prune,
    reset_opacity,
    select_rows,
    view_space_grad,
)
from facade_pipeline.training.init import initial_model, sample_mesh
from facade_pipeline.training.model import GaussianModel, quat_from_normal, quat_to_rotmat
from facade_pipeline.training.optimizers import gaussian_optimizer
from facade_pipeline.training.ply import model_columns, model_from_ply, read_ply, write_ply
from tests.training.conftest import small_params


def _quad(z: float = 0.0):
    v = np.array([[0, 0, z], [4, 0, z], [4, 2, z], [0, 2, z], [9, 9, 9]], float)  # one unused vertex
    return v, np.array([[0, 1, 2], [0, 2, 3], [4, 4, 4]])  # the last triangle is degenerate


def test_quat_from_normal_rotates_z_onto_the_normal():
    n = torch.nn.functional.normalize(torch.randn(50, 3, dtype=torch.float64), dim=-1)
    n = torch.cat([n, torch.tensor([[0, 0, 1.0], [0, 0, -1.0]], dtype=torch.float64)])
    R = quat_to_rotmat(quat_from_normal(n))
    assert torch.allclose(R[:, :, 2], n, atol=1e-12)
    assert torch.allclose(
        R @ R.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(52, 3, 3), atol=1e-12
    )


def test_sample_mesh_on_the_surface_with_its_normal():
    v, f = _quad(1.5)
    pts, nrm, tri = sample_mesh(v, f, 500, np.random.default_rng(0))
    assert pts.shape == (500, 3) and np.allclose(pts[:, 2], 1.5)
    assert np.all((pts[:, 0] >= 0) & (pts[:, 0] <= 4) & (pts[:, 1] >= 0) & (pts[:, 1] <= 2))
    assert np.allclose(np.abs(nrm[:, 2]), 1.0)
    assert sample_mesh(v, f[2:], 10, np.random.default_rng(0))[0].shape == (0, 3)  # only a degenerate face


def test_initial_model_crops_points_and_orients_mesh_samples():
    v, f = _quad()
    rng = np.random.default_rng(1)
    inside = rng.uniform([0, 0, -0.2], [4, 2, 0.2], (40, 3))
    outside = rng.uniform([50, 50, 50], [60, 60, 60], (30, 3))  # environment points far from the facade
    geom = InitGeometry(np.concatenate([inside, outside]), np.full((70, 3), 0.3), v[:4], f[:2])
    lo, hi = v[:4].min(0), v[:4].max(0)
    m = initial_model(geom, (lo, hi), 1000, 25, 0.5, 3, 0.1, 0.2, 0.9, 0.04, 2, 0, "cpu")
    assert m.n == 40 + 25
    assert m.sh_rest.shape == (65, 8, 3)
    assert torch.allclose(m.opacities(), torch.full((65,), 0.1), atol=1e-6)
    assert torch.allclose(m.reflectivity(), torch.full((65,), 0.2), atol=1e-6)
    assert torch.allclose(m.normals()[40:].abs()[:, 2], torch.ones(25), atol=1e-6)  # in the mesh plane
    rgb = m.sh_dc[:, 0] * 0.28209479177387814 + 0.5
    assert torch.allclose(rgb, torch.full((65, 3), 0.3), atol=1e-6)  # mesh samples take point colours


def test_initial_reflectivity_of_samples_on_glass_triangles():
    """Samples of the corrected mesh's glass triangles start at the glass reflectivity, the rest (coarse
    points, other triangles) at the other; without labels every splat starts at the other."""
    v, f = _quad()
    pts = np.random.default_rng(1).uniform([0, 0, -0.2], [4, 2, 0.2], (40, 3))
    glass = np.array([True, False, False])  # triangle 0 (below the diagonal y = x / 2) is glass
    lo, hi = v[:4].min(0), v[:4].max(0)
    for labels in (glass, None):
        geom = InitGeometry(pts, np.full((40, 3), 0.3), v, f, labels)
        m = initial_model(geom, (lo, hi), 1000, 200, 0.5, 3, 0.1, 0.2, 0.9, 0.04, 2, 0, "cpu")
        r, xy = m.reflectivity(), m.means[:, :2]
        on_glass = torch.zeros(m.n, dtype=torch.bool)
        if labels is not None:
            on_glass[40:] = xy[40:, 1] < xy[40:, 0] / 2
        assert 50 < int(on_glass.sum()) < 150 or labels is None
        assert torch.allclose(r[on_glass], torch.full_like(r[on_glass], 0.9), atol=1e-6)
        assert torch.allclose(r[~on_glass], torch.full_like(r[~on_glass], 0.2), atol=1e-6)


def _model(n: int = 6, seed: int = 0) -> GaussianModel:
    g = torch.Generator().manual_seed(seed)
    return GaussianModel.create(
        torch.randn(n, 3, generator=g),
        torch.randn(n, 4, generator=g),
        torch.rand(n, 2, generator=g) * 0.1 + 0.01,
        torch.rand(n, 3, generator=g),
        0.5,
        0.3,
        0.04,
        1,
    )


def test_select_rows_keeps_adam_moments_with_their_rows():
    m = _model()
    opt = gaussian_optimizer(m, small_params(), 1.0)
    for p in m.params().values():
        p.grad = torch.randn_like(p)
    opt.step()
    before = opt.state[m.means]["exp_avg"].clone()
    keep = torch.tensor([True, False, True, True, False, True])
    select_rows(m, opt, keep)
    assert m.n == 4 and torch.equal(opt.state[m.means]["exp_avg"], before[keep])
    assert all(opt.state[p]["exp_avg"].shape == p.shape for p in m.params().values())
    for p in m.params().values():  # the optimiser still steps
        p.grad = torch.ones_like(p)
    opt.step()


def test_densify_clones_small_splits_large_and_prunes_transparent():
    p = small_params()
    d = p.densify
    m = _model(4)
    with torch.no_grad():
        m.log_scales[:] = torch.log(
            torch.tensor([[0.001, 0.001], [0.001, 0.001], [1.0, 0.5], [0.001, 0.001]])
        )
        m.opacity_logits[3] = -10.0  # transparent: pruned
    opt = gaussian_optimizer(m, p, 1.0)
    stats = DensifyStats(torch.tensor([1.0, 0.0, 1.0, 0.0]), torch.tensor([1.0, 1.0, 1.0, 1.0]))
    counts = densify_and_prune(m, opt, stats, d, 10.0, False, torch.Generator().manual_seed(0))
    assert counts == {"cloned": 1, "split": 1, "pruned": 1}
    # kept: 0, 1 (originals), the clone of 0, two children of 2; dropped: 2 (split) and 3 (transparent)
    assert m.n == 5
    scales = m.scales().detach()
    assert torch.allclose(scales[-2:], torch.tensor([[1.0, 0.5]] * 2) / 1.6, atol=1e-6)
    assert all(
        opt.state.get(p) is None or opt.state[p]["exp_avg"].shape == p.shape for p in m.params().values()
    )


def test_a_clone_and_its_copy_blend_as_the_splat_did():
    """A cloned splat and its copy share its opacity: they composite to the splat's own alpha and colour
    where its Gaussian peaks, and to at most a'^2 / 4 more on its flanks (1 - (1 - a' G)^2 against a G), not
    to 1 - (1 - a)^2 as two copies of a would; a splat left alone keeps its opacity."""
    from facade_pipeline.splatting import render_2dgs

    m = GaussianModel.create(
        torch.tensor([[0.0, 0.0, 5.0], [0.6, 0.2, 5.5]]),
        torch.tensor([[1.0, 0.0, 0.0, 0.0]] * 2),  # facing the camera
        torch.tensor([[0.2, 0.15], [0.2, 0.2]]),
        torch.tensor([[0.9, 0.2, 0.1], [0.1, 0.3, 0.8]]),
        0.7,
        0.3,
        0.04,
        1,
    )
    K = torch.tensor([[100.0, 0, 32.5], [0, 100.0, 24.5], [0, 0, 1]])  # the clone on pixel (32, 24)'s centre

    def colour():  # in [0, 1], so that a colour moves no more than its alpha
        return m.sh_dc[:, 0] * 0.28209479177387814 + 0.5

    def draw():
        with torch.no_grad():
            r = render_2dgs(m.means, m.quats, m.scales(), m.opacities(), colour(), torch.eye(4), K, 64, 48)
        return torch.cat([r.features, r.alpha.unsqueeze(-1)], -1)

    before, a = draw(), float(m.opacities()[0])
    opt = gaussian_optimizer(m, small_params(), 1.0)
    stats = DensifyStats(torch.tensor([1.0, 0.0]), torch.ones(2))
    counts = densify_and_prune(m, opt, stats, small_params().densify, 1000.0, False, torch.Generator())
    assert counts["cloned"] == 1 and m.n == 3
    a_half = 1.0 - (1.0 - a) ** 0.5
    assert torch.allclose(m.opacities().detach(), torch.tensor([a_half, 0.7, a_half]), atol=1e-6)
    after = draw()
    assert float((after - before).abs().max()) <= a_half**2 / 4 + 1e-5
    assert torch.allclose(after[24, 32], before[24, 32], atol=1e-5)  # the clone's centre pixel


def test_densify_respects_the_splat_budget():
    p = small_params(densify_max_gaussians=5)
    m = _model(4)
    opt = gaussian_optimizer(m, p, 1.0)
    stats = DensifyStats(torch.ones(4), torch.ones(4))
    densify_and_prune(m, opt, stats, p.densify, 1000.0, False, torch.Generator().manual_seed(0))
    assert m.n <= 5


def test_opacity_reset_clamps_and_zeroes_moments():
    m = _model()
    opt = gaussian_optimizer(m, small_params(), 1.0)
    for q in m.params().values():
        q.grad = torch.randn_like(q)
    opt.step()
    reset_opacity(m, opt, 0.01)
    assert torch.all(m.opacities() <= 0.01 + 1e-6)
    assert torch.all(opt.state[m.opacity_logits]["exp_avg"] == 0)


def test_view_space_gradient_on_the_optical_axis():
    """For a splat on the optical axis, the formula equals the exact gradient of the loss with respect to
    the projected pixel position, in NDC units (times half the image size)."""
    K = torch.tensor([[100.0, 0, 32], [0, 120.0, 24], [0, 0, 1]], dtype=torch.float64)
    T = torch.eye(4, dtype=torch.float64)
    means = torch.tensor([[0.0, 0.0, 7.0]], dtype=torch.float64, requires_grad=True)
    pc = means @ T[:3, :3].T + T[:3, 3]
    px = K[0, 0] * pc[:, 0] / pc[:, 2] + K[0, 2]
    py = K[1, 1] * pc[:, 1] / pc[:, 2] + K[1, 2]
    a = torch.tensor([0.3, -0.7], dtype=torch.float64)
    (a[0] * px + a[1] * py).sum().backward()
    g, vis = view_space_grad(means, means.grad, T, K, (64, 48), (0, 0, 64, 48), 0.2)
    assert bool(vis[0])
    assert float(g[0]) == pytest.approx(float(torch.hypot(a[0] * 32, a[1] * 24)), rel=1e-12)
    _, vis = view_space_grad(means, means.grad, T, K, (64, 48), (40, 0, 24, 48), 0.2)
    assert not bool(vis[0])  # outside the window


def test_ply_round_trip_and_standard_names(tmp_path):
    m = _model(7)
    write_ply(tmp_path / "g.ply", m)
    cols = read_ply(tmp_path / "g.ply")
    head = (tmp_path / "g.ply").read_bytes()[:2000].decode("ascii", "ignore")
    for name in (
        "x",
        "nx",
        "f_dc_0",
        "f_rest_0",
        "opacity",
        "scale_0",
        "scale_2",
        "rot_0",
        "reflectivity",
        "f0_2",
    ):
        assert f"property float {name}\n" in head
    assert len(cols["f_rest_0"]) == 7 and len([k for k in cols if k.startswith("f_rest_")]) == 9
    back = model_from_ply(cols)
    for name, t in m.state().items():
        ref = t if name != "quats" else m.unit_quats().detach()
        assert torch.allclose(getattr(back, name).detach(), ref, atol=1e-4), name


def test_split_holds_out_every_eighth_view():
    train, test = split_views(20, 8)
    assert test == (0, 8, 16) and set(train) | set(test) == set(range(20)) and not set(train) & set(test)
    assert split_views(1, 8) == ((0,), ())
    assert split_views(5, 0) == (tuple(range(5)), ())


def test_ply_loads_in_the_reader_3dgs_viewers_use_exactly_as_written(tmp_path):
    """plyfile (the reader of the 3DGS reference code and most viewers' converters) sees the same
    properties, in the same order, with the same float32 values, as model_columns wrote."""
    plyfile = pytest.importorskip("plyfile", reason="plyfile is a dev dependency (pip install -e '.[dev]')")
    m = _model(9)
    write_ply(tmp_path / "g.ply", m)
    vertex = plyfile.PlyData.read(str(tmp_path / "g.ply"))["vertex"]
    cols = model_columns(m)
    assert [p.name for p in vertex.properties] == list(cols)
    assert all(p.val_dtype == "f4" for p in vertex.properties) and vertex.count == 9
    for name, values in cols.items():
        assert np.array_equal(np.asarray(vertex[name]), values), name
