"""render_2dgs against the dense float64 reference, between backends, and on the issue's hard cases."""

from __future__ import annotations

import logging
from dataclasses import replace

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from facade_pipeline.splatting import PixelWindow, cpu_kernel, render_2dgs, resolve_backend
from facade_pipeline.splatting.binning import bin_splats, pixel_support_bounds
from facade_pipeline.splatting.blend_torch import BlendSettings, blend_torch
from facade_pipeline.splatting.surfels import project_surfels
from facade_pipeline.splatting.types import LOWPASS_SIGMA_PX
from tests.splatting.dense_reference import render_dense
from tests.splatting.scenes import HARD_CASES, MAP_NAMES, TOL, Scene, camera, hard_case, random_scene

needs_cpp = pytest.mark.skipif(cpu_kernel.load() is None, reason="C++ kernel could not be built")
CPU_BACKENDS = ["torch", pytest.param("cpp", marks=needs_cpp)]


def render(scene: Scene, backend: str, params=None, **kw) -> dict[str, torch.Tensor]:
    params = scene.params() if params is None else params
    r = render_2dgs(*params, scene.cam_from_world, scene.K, scene.width, scene.height, backend=backend, **kw)
    return {k: getattr(r, k) for k in MAP_NAMES}


def maps_and_grads(scene: Scene, fn, seed: int = 0):
    """Maps and the gradients of every splat input for a random linear loss on all six maps."""
    params = [p.detach().clone().requires_grad_() for p in scene.params()]
    maps = fn(params)
    g = torch.Generator().manual_seed(seed)
    # weights drawn in float64 whatever the maps' dtype, so that float32 and float64 runs share the loss
    weights = {k: torch.randn(v.shape, generator=g, dtype=torch.float64).to(v.dtype) for k, v in maps.items()}
    loss = sum((maps[k] * weights[k]).sum() for k in maps)
    grads = torch.autograd.grad(loss, params, allow_unused=True)
    grads = [torch.zeros_like(p) if gr is None else gr for gr, p in zip(grads, params, strict=True)]
    return {k: v.detach() for k, v in maps.items()}, grads


def dense(scene: Scene, **kw):
    return lambda p: render_dense(*p, scene.cam_from_world, scene.K, scene.width, scene.height, **kw)


def assert_close(maps_a, grads_a, maps_b, grads_b, dtype):
    atol, rtol, grad_rtol = TOL[dtype]
    for k in MAP_NAMES:
        a, b = maps_a[k].double(), maps_b[k].double()
        assert a.shape == b.shape, k
        excess = ((a - b).abs() - atol - rtol * b.abs()).max().item() if a.numel() else 0.0
        assert excess <= 0, f"{k}: error exceeds {atol} + {rtol} |ref| by {excess:.3g}"
    names = ("means", "quats", "scales", "opacities", "features")
    for name, a, b in zip(names, grads_a, grads_b, strict=True):
        scale = max(b.abs().max().item() if b.numel() else 0.0, 1e-3)
        err = (a.double() - b.double()).abs().max().item() if a.numel() else 0.0
        assert err <= grad_rtol * scale, f"d/d{name}: max error {err:.3g} > {grad_rtol} x {scale:.3g}"


def assert_finite(maps, grads):
    for k, v in maps.items():
        assert torch.isfinite(v).all(), k
    for g in grads:
        assert torch.isfinite(g).all()


# --- smoke and shapes -------------------------------------------------------------------------------------


@pytest.mark.parametrize("backend", CPU_BACKENDS)
def test_shapes_and_ranges(backend):
    scene = random_scene(1, channels=6)
    maps = render(scene, backend)
    H, W = scene.height, scene.width
    assert maps["features"].shape == (H, W, 6) and maps["normal"].shape == (H, W, 3)
    for k in ("alpha", "depth_expected", "depth_median", "distortion"):
        assert maps[k].shape == (H, W)
    assert (maps["alpha"] >= 0).all() and (maps["alpha"] <= 1).all() and maps["alpha"].max() > 0.5
    covered = maps["alpha"] > 0.5
    assert (maps["depth_expected"][covered] > 0.2).all()
    # normals face the camera (at the origin, looking down +z): n . (o - X) >= 0, i.e. n_z <= 0 mostly
    assert (maps["normal"][covered][:, 2] <= 1e-9).all()


# --- exactness: dense reference, between backends, gradcheck --------------------------------------------


@pytest.mark.parametrize("backend", CPU_BACKENDS)
@pytest.mark.parametrize("seed", [0, 1])
def test_float64_matches_dense_reference(backend, seed):
    scene = random_scene(seed)
    ref = maps_and_grads(scene, dense(scene))
    got = maps_and_grads(scene, lambda p: render(scene, backend, p))
    assert_close(*got, *ref, torch.float64)


@pytest.mark.parametrize("backend", CPU_BACKENDS)
def test_float32_matches_dense_reference(backend):
    scene = random_scene(3)
    ref = maps_and_grads(scene, dense(scene))
    s32 = scene.to(torch.float32)
    got = maps_and_grads(s32, lambda p: render(s32, backend, p))
    assert_close(*got, *ref, torch.float32)


@needs_cpp
def test_cpp_equals_torch_backend_float32():
    scene = random_scene(5, n=150, width=70, height=45, channels=3).to(torch.float32)
    a = maps_and_grads(scene, lambda p: render(scene, "torch", p))
    b = maps_and_grads(scene, lambda p: render(scene, "cpp", p))
    assert_close(*a, *b, torch.float32)


@pytest.mark.parametrize("backend", CPU_BACKENDS)
def test_gradcheck_float64(backend):
    scene = random_scene(11, n=5, width=14, height=11, channels=2)
    scene = replace(scene, means=scene.means * 0.3 + torch.tensor([0, 0, -1.0], dtype=torch.float64))

    def fn(*params):
        return tuple(render(scene, backend, list(params)).values())

    params = [p.detach().clone().requires_grad_() for p in scene.params()]
    assert render(scene, backend)["alpha"].max() > 0.3  # the splats are in view
    # fast mode (random projections of the Jacobian) keeps the slow pure-torch backend under a few seconds
    assert torch.autograd.gradcheck(fn, params, eps=1e-6, atol=1e-6, rtol=1e-5, fast_mode=backend == "torch")


# --- the low-pass filter's sigma --------------------------------------------------------------------------


@pytest.mark.parametrize("backend", CPU_BACKENDS)
@pytest.mark.parametrize("sigma", [0.3, 0.5, 1.2])
def test_lowpass_sigma_matches_dense_reference(backend, sigma):
    """Another low-pass sigma, maps and gradients, against the dense reference; small splats, so that many
    pixels take the low-pass branch. 1.2 px widens the support beyond 2DGS's: bounds computed for the
    default sigma would drop pixels and fail this."""
    scene = random_scene(4, n=60)
    scene = replace(scene, scales=scene.scales * 0.2)
    ref = maps_and_grads(scene, dense(scene, lowpass_sigma_px=sigma))
    got = maps_and_grads(scene, lambda p: render(scene, backend, p, lowpass_sigma_px=sigma))
    assert_close(*got, *ref, torch.float64)
    default = render(scene, backend)["alpha"]
    assert (got[0]["alpha"] - default).abs().max() > 0.05  # the sigma changes the image


@pytest.mark.parametrize("backend", CPU_BACKENDS)
@pytest.mark.parametrize("sigma", [0.35, 0.5, LOWPASS_SIGMA_PX, 0.7071, 1.5])
def test_point_like_splat_renders_as_the_lowpass_gaussian(backend, sigma):
    """A splat far smaller than a pixel is all low-pass: at a pixel centre d px from its projected centre,
    alpha = opacity exp(-d^2 / (2 sigma^2)), and nothing where that is below 1/255."""
    cw, K = camera(32, 24, 100.0)
    centre = torch.tensor([[0.013, -0.008, 5.0]], dtype=torch.float64)  # projects to (16.26, 11.84)
    f64 = {"dtype": torch.float64}
    r = render_2dgs(centre, torch.tensor([[1.0, 0, 0, 0]], **f64), torch.full((1, 2), 1e-6, **f64),
                    torch.tensor([0.9], **f64), torch.ones(1, 1, **f64), cw, K, 32, 24, backend=backend,
                    lowpass_sigma_px=sigma)
    ys, xs = torch.meshgrid(torch.arange(24.0, dtype=torch.float64) + 0.5,
                            torch.arange(32.0, dtype=torch.float64) + 0.5, indexing="ij")
    d2 = (xs - 16.26) ** 2 + (ys - 11.84) ** 2
    exact = LOWPASS_SIGMA_PX if sigma == 0.7071 else sigma  # within 1e-4 px of 2DGS's sigma: 2DGS's
    expected = 0.9 * torch.exp(-0.5 * d2 / exact**2)
    expected = torch.where(expected >= 1 / 255, expected, 0.0)
    torch.testing.assert_close(r.alpha, expected, atol=1e-9, rtol=1e-9)


def test_gsplat_is_refused_or_replaced_for_another_lowpass_sigma(monkeypatch, caplog):
    """gsplat has 2DGS's sigma built in: another sigma asked of it explicitly is an error; with "auto" the
    torch backend renders instead, with one warning. 0.7071 (a config file's) counts as 2DGS's sigma."""
    import facade_pipeline.splatting.render as render_module

    s = random_scene(0, n=6)
    args = s.params() + [s.cam_from_world, s.K, s.width, s.height]
    ref = render_2dgs(*args, backend="torch", lowpass_sigma_px=0.5)
    monkeypatch.setattr(render_module, "resolve_backend", lambda backend, device: "gsplat")
    monkeypatch.setattr(render_module, "_WARNED", set())
    with pytest.raises(ValueError, match="gsplat backend's low-pass filter is fixed"):
        render_2dgs(*args, backend="gsplat", lowpass_sigma_px=0.5)
    with caplog.at_level(logging.WARNING):
        got = render_2dgs(*args, backend="auto", lowpass_sigma_px=0.5)
        render_2dgs(*args, backend="auto", lowpass_sigma_px=0.5)
    assert caplog.text.count("rendering with torch") == 1
    for k in MAP_NAMES:
        torch.testing.assert_close(getattr(got, k), getattr(ref, k), atol=0, rtol=0)
    with pytest.raises(ValueError, match="CUDA"):  # 2DGS's sigma goes to gsplat, which needs CUDA tensors
        render_2dgs(*args, backend="auto", lowpass_sigma_px=0.7071)


def test_a_missing_cpp_kernel_is_warned_about_once(monkeypatch, caplog):
    """Every training step renders: the fallback to the torch backend is logged once per process, and the
    torch backend then renders what the kernel would."""
    import facade_pipeline.splatting.render as render_module

    s = random_scene(1, n=6)
    args = s.params() + [s.cam_from_world, s.K, s.width, s.height]
    ref = render_2dgs(*args, backend="torch")
    monkeypatch.setattr(render_module, "_WARNED", set())
    monkeypatch.setattr(render_module.cpu_kernel, "load", lambda: None)
    with caplog.at_level(logging.WARNING):
        got = [render_2dgs(*args, backend="cpp") for _ in range(3)]
    assert caplog.text.count("C++ kernel unavailable") == 1
    for k in MAP_NAMES:
        torch.testing.assert_close(getattr(got[-1], k), getattr(ref, k), atol=0, rtol=0)


def test_torch_backend_is_independent_of_chunking():
    """Memory bounding (tile groups, depth chunks, carried state) does not change the result."""
    scene = random_scene(4, n=90)
    proj = project_surfels(*scene.params()[:3], scene.cam_from_world, scene.K)
    bins = bin_splats(pixel_support_bounds(proj.ray_transform, scene.opacities, 0.2), proj.depth,
                      PixelWindow(0, 0, scene.width, scene.height))
    args = (proj.ray_transform, scene.opacities, scene.features, proj.normal_world, bins)
    a = blend_torch(*args, BlendSettings(near=0.2, far=100.0))
    b = blend_torch(*args, BlendSettings(near=0.2, far=100.0, chunk=3, pair_budget=256 * 3))
    for x, y in zip(a, b, strict=True):
        torch.testing.assert_close(x, y, atol=1e-12, rtol=0)


@pytest.mark.parametrize("backend", CPU_BACKENDS)
def test_crop_equals_window_of_full_render(backend):
    scene = random_scene(2, width=45, height=38)
    full = render(scene, backend)
    win = PixelWindow(x0=7, y0=19, width=21, height=17)
    crop = render(scene, backend, crop=win)
    for k in MAP_NAMES:
        torch.testing.assert_close(crop[k], full[k][19:36, 7:28], atol=1e-12, rtol=0)
    ref = render_dense(*scene.params(), scene.cam_from_world, scene.K, scene.width, scene.height,
                       x0=7, y0=19, crop_w=21, crop_h=17)
    torch.testing.assert_close(crop["features"], ref["features"], atol=1e-9, rtol=0)


# --- hard cases -------------------------------------------------------------------------------------------


@pytest.mark.parametrize("backend", CPU_BACKENDS)
@pytest.mark.parametrize("case", HARD_CASES)
def test_hard_case_finite_and_exact(case, backend):
    scene = hard_case(case)
    got = maps_and_grads(scene, lambda p: render(scene, backend, p))
    assert_finite(*got)
    ref = maps_and_grads(scene, dense(scene))
    assert_close(*got, *ref, torch.float64)


@pytest.mark.parametrize("backend", CPU_BACKENDS)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_empty_scene(backend, dtype):
    scene = random_scene(0, n=0).to(dtype)
    maps = render(scene, backend)
    assert maps["features"].shape == (scene.height, scene.width, 4)
    for v in maps.values():
        assert (v == 0).all()


def test_hard_cases_show_expected_behaviour():
    """Beyond finiteness: what the hard cases must look like."""
    far = hard_case("far_outside")
    # splat 0 lies far off to the side: removing it changes nothing (splat 1, 100 km ahead, is a low-pass dot)
    without = replace(far, opacities=far.opacities * torch.tensor([0, 1, 1, 1, 1, 1.0], dtype=torch.float64))
    for k, v in render(far, "torch").items():
        torch.testing.assert_close(v, render(without, "torch")[k], atol=0, rtol=0)
    assert (render(hard_case("covers_image"), "torch")["alpha"] > 0.5).all()
    zero = hard_case("opacity_0_and_1")  # splat 0 has opacity 0: its features never show
    loud = replace(zero, features=zero.features.index_fill(0, torch.tensor([0]), 100.0))
    torch.testing.assert_close(render(zero, "torch")["features"], render(loud, "torch")["features"])
    edge = hard_case("edge_on")  # seen exactly edge-on through the centre: only the low-pass blob remains
    assert render(edge, "torch")["alpha"].max() > 0


@pytest.mark.parametrize("backend", CPU_BACKENDS)
@settings(max_examples=25, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    seed=st.integers(0, 10_000),
    log_scale=st.floats(-12, 7),
    tilt=st.floats(-1e-6, 1e-6) | st.floats(-1.0, 1.0),
    depth=st.floats(-3.0, 6.0),
    opacity=st.sampled_from([0.0, 1 / 255, 0.004, 0.5, 0.99, 1.0]),
)
def test_property_finite_forward_and_backward(backend, seed, log_scale, tilt, depth, opacity):
    """Extreme scales, orientations near edge-on, centres behind the camera or across the near plane and
    boundary opacities never produce NaN or Inf, and the backends agree with the dense reference."""
    scene = random_scene(seed, n=4, width=20, height=18, channels=2)
    means = scene.means.clone()
    means[0] = torch.tensor([0.1, -0.2, depth], dtype=torch.float64)
    scales = scene.scales.clone()
    scales[0] = 10.0**log_scale
    quats = scene.quats.clone()
    quats[0] = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=torch.float64)
    quats[1] = torch.tensor([2 ** -0.5, 2 ** -0.5 + tilt, 0.0, 0.0], dtype=torch.float64)
    ops = scene.opacities.clone()
    ops[0] = opacity
    scene = replace(scene, means=means, scales=scales, quats=quats, opacities=ops)
    got = maps_and_grads(scene, lambda p: render(scene, backend, p))
    assert_finite(*got)
    ref = maps_and_grads(scene, dense(scene))
    assert_close(*got, *ref, torch.float64)


# --- errors and backend choice ----------------------------------------------------------------------------


def test_bad_inputs_raise():
    s = random_scene(0, n=3)
    args = s.params() + [s.cam_from_world, s.K, s.width, s.height]
    with pytest.raises(ValueError, match="scales"):
        render_2dgs(*args[:2], torch.ones(3, 3, dtype=torch.float64), *args[3:])
    with pytest.raises(ValueError, match="features"):
        render_2dgs(*args[:4], torch.ones(3, dtype=torch.float64), *args[5:])
    with pytest.raises(ValueError, match="dtype"):
        render_2dgs(args[0].float(), *args[1:])
    with pytest.raises(ValueError, match="crop window"):
        render_2dgs(*args, crop=PixelWindow(30, 0, 10, 5))
    with pytest.raises(ValueError, match="near"):
        render_2dgs(*args, near=0.0)
    with pytest.raises(ValueError, match="gsplat"):
        render_2dgs(*args, backend="gsplat")
    for bad in (0.0, -0.5, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="low-pass sigma"):
            render_2dgs(*args, lowpass_sigma_px=bad)


def test_auto_backend_on_cpu_falls_back_to_torch_with_warning(monkeypatch, caplog):
    expected = "cpp" if cpu_kernel.load() is not None else "torch"
    assert resolve_backend("auto", torch.device("cpu")) == expected
    monkeypatch.setattr(cpu_kernel, "load", lambda: None)
    with caplog.at_level(logging.WARNING):
        assert resolve_backend("auto", torch.device("cpu")) == "torch"
    assert "C++ kernel unavailable" in caplog.text


@needs_cpp
@pytest.mark.parametrize("sigma", [LOWPASS_SIGMA_PX, 0.4, 1.3])
@pytest.mark.parametrize("case", ["random", "crossing_near_plane", "huge_scale", "covers_image",
                                  "behind_camera"])
def test_cpp_binning_equals_torch_binning(case, sigma):
    scene = random_scene(9, n=200, width=70, height=50) if case == "random" else hard_case(case)
    window = PixelWindow(3, 2, scene.width - 5, scene.height - 4)
    proj = project_surfels(*scene.params()[:3], scene.cam_from_world, scene.K)
    bounds = pixel_support_bounds(proj.ray_transform, scene.opacities, 0.2, lowpass_sigma_px=sigma)
    a = bin_splats(bounds, proj.depth, window)
    b = cpu_kernel.bin_splats_cpp(proj.ray_transform, scene.opacities, proj.depth, window, 0.2,
                                  lowpass_sigma_px=sigma)
    assert torch.equal(a.offsets, b.offsets) and torch.equal(a.splat_ids, b.splat_ids)
    finite = torch.isfinite(a.bounds)
    assert torch.equal(finite, torch.isfinite(b.bounds))
    torch.testing.assert_close(a.bounds[finite], b.bounds[finite], rtol=1e-9, atol=1e-9)


@needs_cpp
def test_cpp_gradients_repeat_bit_for_bit_on_several_threads():
    """The kernel's backward deals the tiles to its threads in a fixed order: a fit run again, or in
    another process on as many threads (evaluate's fanned-out alignments), gives the same bits."""
    scene = random_scene(7, n=300, width=130, height=97, channels=3).to(torch.float32)
    torch.set_num_threads(4)  # the autouse fixture sets one (reproducible anyway) and restores
    runs = [maps_and_grads(scene, lambda p: render(scene, "cpp", p))[1] for _ in range(6)]
    for grads in runs[1:]:
        assert all(torch.equal(a, b) for a, b in zip(runs[0], grads, strict=True))
