"""Reflected rays that meet the facade itself (``shading.self_hits``): hits against hand-worked cases and a
brute-force ray-triangle reference, the MLP's use of them, hard cases, and the saved model."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from facade_pipeline.shading.reflection import ReflectionMLP, ReflectionMLPModule, build_reflection_module
from facade_pipeline.shading.self_hits import SELF_HIT_DIM, FacadeHits

pytest.importorskip("open3d")


def _box(lo, hi, start: int):
    """An axis-aligned box's 8 vertices and 12 triangles (outward winding), indices from ``start``."""
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    v = np.array(
        [[x, y, z] for z in (z0, z1) for y in (y0, y1) for x in (x0, x1)], dtype=np.float64
    )  # index = 4 z + 2 y + x
    quads = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
    f = [(a, b, c) for a, b, c, d in quads] + [(a, c, d) for a, b, c, d in quads]
    return v, np.array(f) + start


def _facade():
    """Glass y = 0 (x in [-2, 4], z in [0, 3], facing +y) with one bar proud of it by 0.12 m over
    x in [1, 1.3]: vertices, triangles, glass labels."""
    glass_v = np.array([[-2, 0, 0], [4, 0, 0], [4, 0, 3], [-2, 0, 3]], dtype=np.float64)
    glass_f = np.array([[0, 2, 1], [0, 3, 2]])
    bar_v, bar_f = _box((1.0, 0.0, 0.0), (1.3, 0.12, 3.0), start=4)
    glass = np.arange(2 + len(bar_f)) < 2
    return np.concatenate([glass_v, bar_v]), np.concatenate([glass_f, bar_f]), glass


def _hits(offset=0.02, max_m=0.0) -> FacadeHits:
    v, f, g = _facade()
    return FacadeHits(torch.as_tensor(v), torch.as_tensor(f), torch.as_tensor(g), offset, max_m)


def _unit(*w) -> list[float]:
    a = np.asarray(w, float)
    return (a / np.linalg.norm(a)).tolist()


def test_hits_on_a_proud_bar_worked_by_hand():
    hits = _hits()
    x = torch.tensor([[0.5, 0.0, 1.0], [0.5, 0.0, 1.0], [0.5, 0.0, 1.0], [2.0, 0.0, 1.0]])
    w = torch.tensor(
        [
            _unit(1.0, 0.1, 0.0),  # grazing toward the bar: meets its left side
            _unit(0.0, 1.0, 0.0),  # straight out: escapes
            _unit(1.0, 0.5, 0.0),  # steeply enough to clear the bar's front (0.12 m at 0.5 m away)
            _unit(-1.0, 0.1, 0.0),  # from the right of the bar, back toward it: meets its right side
        ]
    )
    out = hits(x, w)
    assert out.shape == (4, SELF_HIT_DIM)
    assert out[:, 0].tolist() == [1.0, 0.0, 0.0, 1.0]
    # the side that is seen, facing the ray
    assert torch.allclose(out[0, 1:4], torch.tensor([-1.0, 0.0, 0.0]), atol=1e-6)
    assert torch.allclose(out[3, 1:4], torch.tensor([1.0, 0.0, 0.0]), atol=1e-6)
    # distance over the facade's diagonal: from x + 0.02 w to the plane x = 1 (resp. 1.3)
    diag = float(np.linalg.norm([6.0, 0.12, 3.0]))
    w0, w3 = w[0].double(), w[3].double()
    assert out[0, 4].item() == pytest.approx((0.5 / w0[0].item() - 0.02) / diag, rel=1e-4)
    assert out[3, 4].item() == pytest.approx((0.7 / -w3[0].item() - 0.02) / diag, rel=1e-4)
    assert torch.all(out[[1, 2]] == 0)


def test_hits_beyond_the_maximum_distance_are_misses():
    x = torch.tensor([[0.5, 0.0, 1.0], [-1.5, 0.0, 1.0]])
    w = torch.tensor([_unit(1.0, 0.02, 0.0), _unit(1.0, 0.02, 0.0)])  # 0.5 m and 2.5 m from the bar
    assert _hits(max_m=0.0)(x, w)[:, 0].tolist() == [1.0, 1.0]
    assert _hits(max_m=1.0)(x, w)[:, 0].tolist() == [1.0, 0.0]


def test_offset_keeps_rays_off_the_surface_they_leave():
    # a ray leaving the glass at a grazing angle: with no offset open3d may find the glass itself at t ~ 0
    x = torch.tensor([[-1.0, 0.0, 1.0]])
    w = torch.tensor([_unit(-1.0, 0.05, 0.3)])  # away from the bar: nothing to hit
    assert _hits(offset=0.02)(x, w)[0, 0].item() == 0.0


def _brute_force(v, f, glass, o, d):
    """Each ray's hit (t, unit wound normal) by testing every triangle (Moller-Trumbore): the first hit,
    unless it is on a glass triangle's back; then the next one unless that is also a glass triangle's
    back; else none."""
    p0, p1, p2 = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    e1, e2 = p1 - p0, p2 - p0
    t_best = np.full(len(o), np.inf)
    n_best = np.zeros((len(o), 3))
    for i in range(len(o)):
        h = np.cross(d[i], e2)
        a = (e1 * h).sum(1)
        ok = np.abs(a) > 1e-12
        inv = np.where(ok, 1.0 / np.where(ok, a, 1.0), 0.0)
        s = o[i] - p0
        u = inv * (s * h).sum(1)
        q = np.cross(s, e1)
        vv = inv * (q * d[i]).sum(1)
        t = inv * (e2 * q).sum(1)
        hit = ok & (u >= 0) & (vv >= 0) & (u + vv <= 1) & (t > 1e-9)
        order = np.flatnonzero(hit)[np.argsort(t[hit])]
        normals = np.cross(e1[order], e2[order])
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        counts = ((normals @ d[i]) < 0) | ~glass[order]
        k = 0 if len(order) and counts[0] else 1
        if k < len(order) and counts[k]:
            t_best[i], n_best[i] = t[order[k]], normals[k]
    return t_best, n_best


def test_hits_match_a_brute_force_reference():
    rng = np.random.default_rng(3)
    v, f, glass = _facade()
    # a second bar and a frame strip hanging over the glass (a corrected mesh's frames do), and rays from
    # random glass points in random outward directions
    bar_v, bar_f = _box((-1.0, 0.0, 0.5), (-0.7, 0.3, 2.5), start=len(v))
    strip_v = np.array([[2.0, 0.1, 0.0], [2.5, 0.1, 0.0], [2.5, 0.1, 3.0], [2.0, 0.1, 3.0]])
    strip_f = np.array([[0, 2, 1], [0, 3, 2]]) + len(v) + len(bar_v)
    v, f = np.concatenate([v, bar_v, strip_v]), np.concatenate([f, bar_f, strip_f])
    glass = np.concatenate([glass, np.zeros(len(bar_f) + 2, bool)])
    n = 400
    x = np.stack([rng.uniform(-2, 4, n), np.zeros(n), rng.uniform(0, 3, n)], 1)
    w = rng.normal(size=(n, 3))
    w[:, 1] = np.abs(w[:, 1]) * 0.3  # mostly grazing, so that many rays meet a bar
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    hits = FacadeHits(torch.as_tensor(v), torch.as_tensor(f), torch.as_tensor(glass), 0.02, 0.0)
    out = hits(torch.as_tensor(x, dtype=torch.float32), torch.as_tensor(w, dtype=torch.float32)).double()
    t_ref, n_ref = _brute_force(v, f, glass, x + 0.02 * w, w)
    hit_ref = np.isfinite(t_ref)
    assert 0.1 < hit_ref.mean() < 0.9  # the test exercises both outcomes
    got = out[:, 0].numpy() > 0.5
    # float32 rays may flip a hit that grazes an edge; nothing else
    assert (got != hit_ref).sum() <= 2
    both = got & hit_ref
    n_ref = n_ref * -np.sign((n_ref * w).sum(1, keepdims=True))
    assert np.allclose(out[both, 1:4].numpy(), n_ref[both], atol=1e-4)
    diag = np.linalg.norm(v.max(0) - v.min(0))
    assert np.allclose(out[both, 4].numpy(), np.minimum(t_ref[both] / diag, 1.0), atol=1e-4)


def test_hard_inputs_give_finite_misses():
    hits = _hits()
    x = torch.tensor([[np.nan, 0.0, 1.0], [0.5, 0.0, 1.0], [0.5, 0.0, 1.0], [1e9, 0.0, 1.0]])
    w = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 0.0], [np.inf, 0.0, 0.0], [1.0, 0.1, 0.0]])
    out = hits(x, w)
    assert torch.isfinite(out).all() and torch.all(out == 0)
    assert hits(torch.zeros(0, 3), torch.zeros(0, 3)).shape == (0, SELF_HIT_DIM)
    with pytest.raises(ValueError, match="triangles"):
        FacadeHits(torch.zeros(3, 3), torch.zeros(0, 3, dtype=torch.long), None, 0.02, 0.0)
    with pytest.raises(ValueError, match=">= 0"):
        FacadeHits(*(torch.as_tensor(a) for a in _facade()), -0.1, 0.0)
    v, f, g = (torch.as_tensor(a) for a in _facade())
    with pytest.raises(ValueError, match="glass label per triangle"):
        FacadeHits(v, f, g[:-1], 0.02, 0.0)


LO, HI = torch.tensor([-2.0, -0.5, 0.0]), torch.tensor([4.0, 0.5, 3.0])


def _mlp_cfg(**kw) -> ReflectionMLP:
    return ReflectionMLP(fourier_levels=3, depth=4, width=16, self_hits=True, **kw)


def _mesh():
    v, f, g = _facade()
    return torch.as_tensor(v, dtype=torch.float32), torch.as_tensor(f), torch.as_tensor(g)


def _norm(x: torch.Tensor) -> torch.Tensor:
    return 2.0 * (x - LO) / (HI - LO) - 1.0


def test_mlp_gets_the_hits_and_ignores_the_proxy_where_a_ray_hits():
    with pytest.raises(ValueError, match="corrected mesh"):
        ReflectionMLPModule(_mlp_cfg(), (LO, HI))
    cfg = _mlp_cfg(proxy_channels=2, proxy_resolution_px=16, proxy_levels=1)
    torch.manual_seed(0)
    m = build_reflection_module(cfg, "cpu", (LO, HI), _mesh())
    assert m.second[0].in_features == 16 + 18 + 18 + 5 + SELF_HIT_DIM
    x = _norm(torch.tensor([[0.5, 0.0, 1.0], [0.5, 0.0, 1.0]]))
    w = torch.tensor([_unit(1.0, 0.1, 0.0), _unit(0.0, 1.0, -0.2)])  # the first meets the bar
    before = m(x, w)
    with torch.no_grad():
        for p in m.proxy.parameters():
            p.add_(torch.randn_like(p))
    after = m(x, w)
    assert torch.equal(after[0], before[0])  # the hit ray never reads the proxy
    assert not torch.allclose(after[1], before[1])  # the escaping one does
    # gradients reach the network, not the mesh
    out = m(x.requires_grad_(), w)
    out.sum().backward()
    assert x.grad is not None and torch.isfinite(x.grad).all()
    assert not m.self_hits.vertices.requires_grad


def test_saved_model_with_self_hits_renders_the_same(tmp_path):
    from facade_pipeline.evaluation.render_views import load_trained
    from facade_pipeline.shading.reflection import reflection_record
    from facade_pipeline.training.trained import TrainedModelFiles

    cfg = _mlp_cfg()
    torch.manual_seed(1)
    m = build_reflection_module(cfg, "cpu", (LO, HI), _mesh())
    record = reflection_record(cfg, (LO.numpy(), HI.numpy()), m)
    assert "mesh" in record and not any("vertices" in k for k in record["state_dict"])
    torch.save(record, tmp_path / "reflection.pt")
    # the rest of a variant, so that load_trained finds one
    from facade_pipeline.training.model import GaussianModel
    from facade_pipeline.training.ply import write_ply

    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]] * 2)
    g = GaussianModel.create(torch.zeros(2, 3), quats, torch.full((2, 2), 0.1), torch.full((2, 3), 0.5),
                             0.5, 0.3, 0.04, 1)  # fmt: skip
    write_ply(tmp_path / "gaussians.ply", g)
    (tmp_path / "split.json").write_text('{"train": [], "test": []}')
    params = {"refl_threshold": 0.01, "sh_degree": 1, "sh_degree_interval": 0, "iterations": 1, "near_m": 0.1}
    (tmp_path / "params.json").write_text(json.dumps(params))
    tm = load_trained(TrainedModelFiles.from_dir(tmp_path))
    x = _norm(torch.tensor([[0.5, 0.0, 1.0], [0.5, 0.0, 1.0]]))
    w = torch.tensor([_unit(1.0, 0.1, 0.0), _unit(0.0, 1.0, -0.2)])
    assert torch.equal(tm.reflection(x, w), m(x, w))
    # a record without the mesh: one clear error naming the file
    del record["mesh"]
    torch.save(record, tmp_path / "reflection.pt")
    from facade_pipeline.errors import InputError

    with pytest.raises(InputError, match="reflection.pt"):
        load_trained(TrainedModelFiles.from_dir(tmp_path))


def test_ray_from_just_behind_the_glass_goes_through_it():
    # X_r 1 mm behind the glass (a rendered depth a little too far) with a grazing w: the glass is met from
    # behind at once; the ray goes on and meets the bar, as it would from the glass itself
    x = torch.tensor([[0.5, -0.001, 1.0], [-1.0, -0.001, 1.0]])
    w = torch.tensor([_unit(1.0, 0.1, 0.0), _unit(-1.0, 0.05, 0.3)])
    out = _hits(offset=0.0)(x, w)
    assert out[:, 0].tolist() == [1.0, 0.0]
    assert torch.allclose(out[0, 1:4], torch.tensor([-1.0, 0.0, 0.0]), atol=1e-6)


def test_frame_strip_met_from_behind_is_a_hit_glass_is_not():
    # a frame strip 0.1 m in front of the glass over x in [2, 2.5] (no side faces): a ray leaving the glass
    # under it meets its back, where the true ray would meet the bar's side; without labels every triangle
    # is taken for glass and the ray goes on
    v, f, g = _facade()
    strip_v = np.array([[2.0, 0.1, 0.0], [2.5, 0.1, 0.0], [2.5, 0.1, 3.0], [2.0, 0.1, 3.0]])
    v = np.concatenate([v, strip_v])
    f = np.concatenate([f, np.array([[0, 2, 1], [0, 3, 2]]) + len(v) - 4])
    g = np.concatenate([g, [False, False]])
    x = torch.tensor([[1.8, 0.0, 1.0]])
    w = torch.tensor([_unit(1.0, 0.2, 0.0)])  # reaches y = 0.1 at x = 2.3, under the strip
    labelled = FacadeHits(torch.as_tensor(v), torch.as_tensor(f), torch.as_tensor(g), 0.0, 0.0)(x, w)
    assert labelled[0, 0].item() == 1.0
    assert torch.allclose(labelled[0, 1:4], torch.tensor([0.0, -1.0, 0.0]), atol=1e-6)  # facing the ray
    unlabelled = FacadeHits(torch.as_tensor(v), torch.as_tensor(f), None, 0.0, 0.0)(x, w)
    assert unlabelled[0, 0].item() == 0.0


def test_training_with_self_hits_saves_and_renders_back(data64, tmp_path):
    """A short run on synthetic64 with self hits: some reflected rays meet its frames, everything stays
    finite, and the saved model (the mesh inside reflection.pt) renders what the trainer renders."""
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

    p = small_params(iterations=6, mlp_self_hits=True)
    tr = build_trainer(p, data64, splatting_rasterizer("torch"))
    hits = tr.reflection.self_hits
    seen = []
    forward = hits.forward
    hits.forward = lambda x, w: seen.append(out := forward(x, w)) or out
    train(tr)
    del hits.forward
    flags = torch.cat([o[:, 0] for o in seen])
    assert flags.numel() > 0 and 0.0 < float(flags.mean()) < 1.0  # the frames are met by some rays only
    assert all(torch.isfinite(q).all() for q in tr.reflection.parameters())
    split = {"train": [], "test": []}
    files = TrainedModelFiles.variant(tmp_path, to_dict(p))
    files.save(tr.model, tr.reflection, p.reflection(), data64.bounds, split)
    loaded = load_trained(TrainedModelFiles.from_dir(tmp_path))
    assert loaded.reflection.self_hits is not None
    v = data64.views[data64.test_idx[0]]
    a = render_trained(loaded, v.camera, v.facade_mask)
    b = render_trained(from_trainer(tr, "live"), v.camera, v.facade_mask)
    # The shading has steps (R only where the rendered reflectivity exceeds refl_threshold; the hits are step
    # functions of the ray) and the two render paths give maps that differ by ~1e-8, so a pixel on a step may
    # land on either side: allow one pixel in a thousand to differ, and only a little.
    same = np.isclose(a.rgb, b.rgb, atol=1e-5).all(axis=-1)
    assert same.mean() > 0.999, f"{int((~same).sum())} of {same.size} pixels differ"
    assert np.abs(a.rgb - b.rgb).max() < 0.01
