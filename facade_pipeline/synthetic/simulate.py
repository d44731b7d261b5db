"""Putting a synthetic building together: plan the views, render them one at a time (handing each to a
callback so nothing accumulates over views), and apply the sensor effects that make raw images."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from facade_pipeline.geometry.camera import PinholeCamera
from facade_pipeline.io.colmap import ColmapView
from facade_pipeline.io.images import to_uint8
from facade_pipeline.synthetic.cameras import (
    View,
    check_frontal_views,
    facade_visible,
    frontal_views,
    perturb_pose,
    uav_views,
    with_lens,
)
from facade_pipeline.synthetic.noise import rng_for
from facade_pipeline.synthetic.params import SynthesizeParams
from facade_pipeline.synthetic.render import SceneArrays, Tracer, ViewRender, render_view
from facade_pipeline.synthetic.scene import Scene, build_scene


@dataclass(frozen=True, eq=False)
class Simulator:
    """A built scene with its ray caster and views."""

    scene: Scene
    tracer: Tracer
    arrays: SceneArrays
    views: tuple[View, ...]


def build_simulator(params: SynthesizeParams) -> Simulator:
    """Build the scene, its ray caster, and the views (UAV first, then frontal)."""
    scene = build_scene(params)
    tracer = Tracer(scene.mesh)
    arrays = SceneArrays.of(scene)
    uav = uav_views(scene.parts, params.cameras, params.seed, facade_visible(tracer, arrays))
    frontal = frontal_views(scene.parts, params.cameras)
    if params.has("lens_distortion"):
        frontal = [with_lens(v, params.noise.lens_k1_k2) for v in frontal]
    check_frontal_views(frontal, scene.panels, tracer, arrays)
    return Simulator(scene, tracer, arrays, tuple(uav + frontal))


def raw_camera(params: SynthesizeParams, view: View) -> PinholeCamera:
    """The camera written to raw/ (with "pose_noise", perturbed; else the true one)."""
    if not params.has("pose_noise"):
        return view.camera
    rng = rng_for(params.seed, f"pose_noise_{view.kind}", view.index)
    return perturb_pose(view.camera, rng, params.noise.pose_rotation_deg, params.noise.pose_translation_m)


def raw_view(params: SynthesizeParams, view: View) -> ColmapView:
    """The view as raw/'s COLMAP model holds it: ``raw_camera``'s pose, and through a lens the distorted
    image's intrinsics and size with the lens's k1, k2."""
    cam = raw_camera(params, view)
    if view.lens is None:
        return ColmapView(view.name, cam)
    shot = view.lens.camera
    return ColmapView(view.name, PinholeCamera(shot.K, cam.cam_from_world, shot.width, shot.height),
                      view.lens.k1_k2)


def spread_stops(params: SynthesizeParams, view: View) -> float:
    """The exposure (stops) of ``view`` under "exposure_spread": the views of a kind in turn spread evenly
    over ``noise.exposure_spread_stops`` (the golden ratio's additive recurrence: even for any count)."""
    lo, hi = params.noise.exposure_spread_stops
    return lo + (hi - lo) * ((view.index + 1) * 0.6180339887498949 % 1.0)


def sensor_image(params: SynthesizeParams, view: View, image: np.ndarray) -> np.ndarray:
    """The raw 8-bit image [H, W, 3] from the linear render: exposure gain 2^u, u ~ U(+-exposure_stops)
    ("exposure_change"), times 2^spread_stops ("exposure_spread"), plus N(0, sensor_std) noise per channel
    ("sensor_noise"), then clipped (what a gain takes above 1 is a clipped highlight)."""
    out = np.asarray(image, dtype=np.float64)
    if params.has("exposure_change"):
        u = rng_for(params.seed, f"exposure_{view.kind}", view.index).uniform(-1.0, 1.0)
        out = out * 2.0 ** (u * params.noise.exposure_stops)
    if params.has("exposure_spread"):
        out = out * 2.0 ** spread_stops(params, view)
    if params.has("sensor_noise"):
        rng = rng_for(params.seed, f"sensor_{view.kind}", view.index)
        out = out + rng.normal(0.0, params.noise.sensor_std, size=out.shape)
    return to_uint8(np.clip(out, 0.0, 1.0))


ViewSink = Callable[[View, ViewRender], None]
Progress = Callable[[int, int], None]


def render_all(sim: Simulator, on_view: ViewSink, progress: Progress | None = None) -> dict[str, float]:
    """Render every view in order, calling ``on_view(view, render)`` for each (the caller writes and drops
    it) and ``progress(done, total)`` after each. Returns timings (s)."""
    t_render = t_sink = 0.0
    for k, view in enumerate(sim.views):
        t0 = time.perf_counter()
        ss = sim.scene.params.render.supersample_for(view.kind)
        r = render_view(sim.scene, sim.tracer, sim.arrays, view.camera, ss, view.lens)
        t1 = time.perf_counter()
        on_view(view, r)
        t_render += t1 - t0
        t_sink += time.perf_counter() - t1
        if progress is not None:
            progress(k + 1, len(sim.views))
    return {"render_s": t_render, "write_s": t_sink}
