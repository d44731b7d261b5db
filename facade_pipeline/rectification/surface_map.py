"""Rectification of a frontal view into a metric, fronto-parallel image of its fitted facade surface
(paper, 3.1.1, Fig. 3; extended from curved facades to every frontal view).

The surface (``cylinder.Surface``: a plane or a cylinder with a vertical-ish axis) gets a chart: surface
coordinates (s, h) in metres, s the arc length along the facade from left to right as seen from outside
(a plane's s is plain distance), h the height along the up axis. The rectified image samples the chart on a
regular grid of ``metres_per_px``: rectified pixel (x, y) (centres at i + 0.5) is the surface point

    s = s0 + x m,   h = h0 - y m

so facade up is image up, and a length on the facade is the same number of pixels wherever it is in the
image and however oblique the photo. Both directions are exact, for a plane and a cylinder alike:

- rectified -> original: the chart's point, projected through the view's camera (Eq. 6);
- original -> rectified: the pixel's ray meets the surface (``Surface.intersect``), read in the chart.

For a plane the two are one homography and its inverse (recorded in the mapping file). The paper fits a
7th-order polynomial between the curved facade's pixels and those of its tangent-plane unfolding; here the
unrolled cylinder is exact, and the polynomial (fitted to exact samples, both directions) is kept in the
mapping file as a compact closed form for other tools, with its residual at the samples: it is exact only to
that residual, and the pipeline itself uses the exact maps.

A view is left unrectified ("unrectified") when no surface was fitted: its pixels pass through, with a scale
taken from the coarse mesh's depth at the principal point. It is skipped ("skipped") when its surface is seen
nearly edge-on (the normal further than ``max_view_angle_deg`` from the optical axis) or when its rectified
image would pass ``max_size_factor`` times the view's pixel count.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import cv2
import numpy as np

from facade_pipeline.geometry.camera import PinholeCamera
from facade_pipeline.geometry.polywarp import PolyWarp, fit_polywarp
from facade_pipeline.io.atomic import read_json, write_json
from facade_pipeline.rectification.cylinder import Surface
from facade_pipeline.rectification.params import RectifyParams

Kind = Literal["plane", "cylinder", "unrectified", "skipped"]
WORLD_UP = np.array([0.0, 0.0, 1.0])
#: Samples along each side of a view, borders included, for the canvas extent, the scale and the recorded
#: polynomial: 25 x 25 points over-determine the paper's degree-7 polynomial (36 coefficients per coordinate)
#: about seventeen times. No building ever needed another number: a method constant, not a parameter.
WARP_SAMPLES_PER_SIDE = 25


@dataclass(frozen=True, eq=False)
class Chart:
    """Metric surface coordinates (s, h) on a plane or cylinder (module docstring): origin [3] on the
    surface, unit ``right`` (left to right seen from outside), ``up`` and outward ``normal`` at the origin,
    signed curvature (1/m, > 0: convex toward the normal)."""

    origin: np.ndarray
    right: np.ndarray
    up: np.ndarray
    normal: np.ndarray
    curvature_per_m: float

    @classmethod
    def of(cls, surface: Surface) -> Chart:
        """The chart of ``surface``: up along the cylinder axis (a plane: the world up in the plane), the
        sign toward the world up; right = up x normal, which points right for a viewer outside."""
        n = surface.normal / np.linalg.norm(surface.normal)
        if surface.curvature_per_m == 0.0:
            up = WORLD_UP - (WORLD_UP @ n) * n
            if np.linalg.norm(up) < 1e-6:  # a horizontal plane has no up: take the surface's axis
                up = surface.axis
        else:
            up = surface.axis - (surface.axis @ n) * n
        up = up / np.linalg.norm(up)
        if up @ WORLD_UP < 0:
            up = -up
        return cls(np.asarray(surface.origin, float), np.cross(up, n), up, n, float(surface.curvature_per_m))

    def point(self, s: np.ndarray, h: np.ndarray) -> np.ndarray:
        """World points [N, 3] at chart coordinates s, h [N] (m); finite for every curvature."""
        k = self.curvature_per_m
        s, h = np.asarray(s, float), np.asarray(h, float)
        along = s * np.sinc(k * s / np.pi)  # sin(k s) / k
        depth = -0.5 * k * s * s * np.sinc(k * s / (2.0 * np.pi)) ** 2  # (cos(k s) - 1) / k
        return self.origin + h[:, None] * self.up + along[:, None] * self.right + depth[:, None] * self.normal

    def coords(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Chart coordinates (s, h) [N] (m) of world points [N, 3] on (or near) the surface."""
        q = np.asarray(points, float) - self.origin
        t, w, h = q @ self.right, q @ self.normal, q @ self.up
        k = self.curvature_per_m
        s = t if k == 0.0 else np.arctan2(k * t, 1.0 + k * w) / k
        return s, h

    def to_dict(self) -> dict:
        return {"origin_m": self.origin.tolist(), "right": self.right.tolist(), "up": self.up.tolist(),
                "normal": self.normal.tolist(), "curvature_per_m": self.curvature_per_m}

    @classmethod
    def from_dict(cls, d: dict) -> Chart:
        return cls(*(np.array(d[k], float) for k in ("origin_m", "right", "up", "normal")),
                   float(d["curvature_per_m"]))

    def surface(self) -> Surface:
        return Surface(self.origin, self.up, self.normal, self.curvature_per_m)


@dataclass(frozen=True, eq=False)
class ViewRectification:
    """The hand-off of ``rectify`` for one frontal view: the exact maps between the original image (the
    camera's W x H) and the rectified canvas (width x height), both in pixels with centres at
    (i + 0.5, j + 0.5), and the canvas's scale (m per px). ``chart`` is None for "unrectified" and "skipped"
    views (identity maps); ``reason`` says why a view was not rectified."""

    kind: Kind
    width: int
    height: int
    metres_per_px: float
    camera: PinholeCamera
    chart: Chart | None = None
    s0_m: float = 0.0
    h0_m: float = 0.0
    reason: str = ""
    polynomial: tuple[PolyWarp, PolyWarp] | None = None  # (forward, inverse), cylinders only

    @property
    def rectified(self) -> bool:
        return self.chart is not None

    def to_original(self, xy: np.ndarray) -> np.ndarray:
        """Original-view pixels [N, 2] of rectified pixels ``xy`` [N, 2] (NaN behind the camera)."""
        xy = np.asarray(xy, float).reshape(-1, 2)
        if self.chart is None:
            return xy.copy()
        m = self.metres_per_px
        uv, _ = self.camera.project(self.chart.point(self.s0_m + xy[:, 0] * m, self.h0_m - xy[:, 1] * m))
        return uv

    def to_rectified(self, uv: np.ndarray) -> np.ndarray:
        """Rectified pixels [N, 2] of original-view pixels ``uv`` [N, 2] (NaN where the ray misses)."""
        uv = np.asarray(uv, float).reshape(-1, 2)
        if self.chart is None:
            return uv.copy()
        o, d = self.camera.pixel_rays(uv[:, 0], uv[:, 1])
        lam = self.chart.surface().intersect(o, d)
        s, h = self.chart.coords(o + lam[:, None] * d)
        m = self.metres_per_px
        return np.stack([(s - self.s0_m) / m, (self.h0_m - h) / m], axis=1)

    def homography(self) -> np.ndarray | None:
        """[3, 3] rectified -> original pixels of a plane (exact), None for other kinds."""
        if self.kind != "plane":
            return None
        c, m = self.chart, self.metres_per_px
        R, t = self.camera.cam_from_world[:3, :3], self.camera.cam_from_world[:3, 3]
        # rectified (x, y, 1) -> (s, h, 1) -> world point -> camera -> pixels
        A = np.array([[m, 0.0, self.s0_m], [0.0, -m, self.h0_m], [0.0, 0.0, 1.0]])
        P = np.stack([R @ c.right, R @ c.up, R @ c.origin + t], axis=1)
        H = self.camera.K @ P @ A
        return H / H[2, 2]

    def to_dict(self) -> dict:
        d = {"kind": self.kind, "rectified_width": self.width, "rectified_height": self.height,
             "metres_per_px": self.metres_per_px if np.isfinite(self.metres_per_px) else None,
             "reason": self.reason, "camera": self.camera.to_dict(),
             "chart": None if self.chart is None else self.chart.to_dict(),
             "s0_m": self.s0_m, "h0_m": self.h0_m}
        H = self.homography()
        if H is not None:
            F = np.linalg.inv(H)
            d["homography"] = {"forward": (F / F[2, 2]).tolist(), "inverse": H.tolist()}
        if self.polynomial is not None:
            fwd, inv = self.polynomial
            d["polynomial"] = {"forward": fwd.to_dict(), "inverse": inv.to_dict()}
        return d

    def save(self, path: str | Path) -> None:
        write_json(path, self.to_dict())

    @classmethod
    def load(cls, path: str | Path) -> ViewRectification:
        def parse(d: dict) -> ViewRectification:
            poly = d.get("polynomial")
            return cls(d["kind"], int(d["rectified_width"]), int(d["rectified_height"]),
                       float("nan") if d["metres_per_px"] is None else float(d["metres_per_px"]),
                       PinholeCamera.from_dict(d["camera"]),
                       None if d["chart"] is None else Chart.from_dict(d["chart"]),
                       float(d["s0_m"]), float(d["h0_m"]), str(d["reason"]),
                       None if poly is None else (PolyWarp.from_dict(poly["forward"]),
                                                  PolyWarp.from_dict(poly["inverse"])))

        return read_json(path, "a rectification (JSON with kind, sizes, scale, camera and chart)", parse)

    @classmethod
    def unrectified(cls, camera: PinholeCamera, metres_per_px: float, reason: str,
                    kind: Kind = "unrectified") -> ViewRectification:
        return cls(kind, camera.width, camera.height, float(metres_per_px), camera, reason=reason)


def image_grid(width: int, height: int, n: int) -> np.ndarray:
    """[n * n, 2] positions on a regular grid spanning [0, W] x [0, H], borders included (px)."""
    xs, ys = np.meshgrid(np.linspace(0.0, width, n), np.linspace(0.0, height, n))
    return np.stack([xs.ravel(), ys.ravel()], axis=1)


def view_angle_deg(camera: PinholeCamera, surface: Surface) -> float:
    """Angle (deg) between the optical axis and the surface normal where the principal point's ray meets
    the surface (90 where it misses)."""
    cx, cy = camera.K[0, 2], camera.K[1, 2]
    o, d = camera.pixel_rays(np.array([cx]), np.array([cy]))
    lam = surface.intersect(o, d)
    if not np.isfinite(lam[0]):
        return 90.0
    chart = Chart.of(surface)
    s, h = chart.coords(o + lam[:, None] * d)
    # the normal at the hit: the chart's normal turned by the arc angle about the up axis
    phi = chart.curvature_per_m * s[0]
    n = np.cos(phi) * chart.normal + np.sin(phi) * chart.right
    return float(np.degrees(np.arccos(np.clip(abs(n @ camera.forward), 0.0, 1.0))))


def rectify_view(camera: PinholeCamera, surface: Surface, params: RectifyParams,
                 s_bounds_m: tuple[float, float] | None = None) -> ViewRectification:
    """The rectification of one view onto ``surface`` (module docstring); "skipped" with the reason when
    the surface is seen nearly edge-on, the view's rays miss it, or the canvas would be too large. With
    ``s_bounds_m`` the canvas spans no more than that range of s (m): the extent of the surface where the
    view also frames another beside it, which the canvas would show mapped onto the wrong surface."""
    W, H = camera.width, camera.height
    angle = view_angle_deg(camera, surface)
    if angle > params.max_view_angle_deg:
        return ViewRectification.unrectified(
            camera, np.nan, f"surface seen {angle:.0f} deg from the optical axis (more than "
            f"max_view_angle_deg = {params.max_view_angle_deg:g}): nearly edge-on", "skipped")
    chart = Chart.of(surface)
    kind: Kind = "plane" if surface.curvature_per_m == 0.0 else "cylinder"
    unit = ViewRectification(kind, 1, 1, 1.0, camera, chart)  # 1 m per px from (0, 0): s, h = x, -y
    px = image_grid(W, H, WARP_SAMPLES_PER_SIDE)
    sh = unit.to_rectified(px) * [1.0, -1.0]
    hit = np.isfinite(sh).all(axis=1)
    if hit.mean() < 0.5:
        return ViewRectification.unrectified(
            camera, np.nan, f"only {hit.mean():.0%} of the view's rays meet the fitted surface", "skipped")
    m = params.metres_per_px if params.metres_per_px != "auto" else ground_sample_m(unit, px[hit])
    lo, hi = sh[hit].min(axis=0), sh[hit].max(axis=0)
    if s_bounds_m is not None:
        lo[0], hi[0] = max(lo[0], s_bounds_m[0]), min(hi[0], s_bounds_m[1])
    width, height = (int(np.ceil(v)) for v in (hi - lo) / m)
    if width * height > params.max_size_factor * W * H:
        return ViewRectification.unrectified(
            camera, np.nan, f"rectified image of {width} x {height} px is more than max_size_factor = "
            f"{params.max_size_factor:g} times the view's {W} x {H}", "skipped")
    rect = ViewRectification(kind, width, height, float(m), camera, chart, float(lo[0]), float(hi[1]))
    if kind == "cylinder":
        rect = _with_polynomial(rect, px[hit], params.warp.degree)
    return rect


def warp_displacement_px(camera: PinholeCamera, surface: Surface) -> float:
    """Largest distance (px) by which the rectification onto ``surface`` moves a pixel of the view beyond
    a rotation, scale and shift of the whole view, at the view's own ground sample distance (so that neither
    ``metres_per_px`` nor the camera's roll counts): 0 for a view straight on to a plane, a fraction of the
    view's size for an oblique one (its far side stretched). Over a ``WARP_SAMPLES_PER_SIDE`` grid of the
    view; NaN when no ray meets the surface."""
    kind: Kind = "plane" if surface.curvature_per_m == 0.0 else "cylinder"
    unit = ViewRectification(kind, 1, 1, 1.0, camera, Chart.of(surface))
    px = image_grid(camera.width, camera.height, WARP_SAMPLES_PER_SIDE)
    sh = unit.to_rectified(px)  # (s, -h) in metres
    hit = np.isfinite(sh).all(axis=1)
    if not hit.any():
        return float("nan")
    xy = sh[hit] / ground_sample_m(unit, px[hit])
    return float(_similarity_residual_px(px[hit], xy).max())


def _similarity_residual_px(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Distances [N] from ``dst`` [N, 2] to the best similarity (rotation, scale, shift) image of ``src``."""
    a, b = src - src.mean(axis=0), dst - dst.mean(axis=0)
    U, S, Vt = np.linalg.svd(b.T @ a)
    D = np.diag([1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    scale = float(np.trace(np.diag(S) @ D)) / max(float((a**2).sum()), 1e-300)
    return np.linalg.norm(b - scale * a @ R.T, axis=1)


def parallax_grid(rect: ViewRectification, step_px: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The parallax coordinate of a rectified canvas (``segmentation.parallax.ParallaxField``) on a grid of
    about ``step_px`` (px), borders included: x positions [Gx], y positions [Gy] and P [Gy, Gx, 2] (px).
    A point standing proud of the surface by e (m) is seen shifted along the surface by e tan(a) away
    from the camera, a the angle of the line of sight from the local normal in the plane of the normal and
    the direction of the shift; P = D tan(a) / m, signed along x and y, with D the camera's distance to the
    surface, so that the shift is (e / D) P px. For a plane P is the distance from the camera's foot
    (linear); on a cylinder it grows faster, without bound toward the silhouette."""
    c, m = rect.chart, rect.metres_per_px
    xs = np.linspace(0.0, rect.width, max(2, int(np.ceil(rect.width / step_px)) + 1))
    ys = np.linspace(0.0, rect.height, max(2, int(np.ceil(rect.height / step_px)) + 1))
    gx, gy = np.meshgrid(xs, ys)
    s = rect.s0_m + gx.ravel() * m
    X = c.point(s, rect.h0_m - gy.ravel() * m)
    phi = (c.curvature_per_m * s)[:, None]  # the normal turns by the arc angle about the up axis
    n = np.cos(phi) * c.normal + np.sin(phi) * c.right
    right = np.cross(c.up, n)
    r = X - rect.camera.center
    depth = np.maximum(np.abs(np.einsum("ij,ij->i", r, n)), 1e-9)  # |r . n|
    D = abs(float(c.surface().signed_distance(rect.camera.center[None])[0]))
    p = np.stack([np.einsum("ij,ij->i", r, right), -(r @ c.up)], axis=1) * (D / m) / depth[:, None]
    return xs, ys, p.reshape(len(ys), len(xs), 2)


def ground_sample_m(unit: ViewRectification, px: np.ndarray) -> float:
    """Median over ``px`` [N, 2] of the square root of one pixel's footprint area on the surface (m);
    ``unit`` is the view's rectification at 1 m per px."""
    e = 0.5
    a = unit.to_rectified(px + [-e, 0.0])
    b = unit.to_rectified(px + [e, 0.0])
    c = unit.to_rectified(px + [0.0, -e])
    d = unit.to_rectified(px + [0.0, e])
    u, v = b - a, d - c
    area = np.abs(u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0])  # m^2 of a 1 x 1 px square
    area = area[np.isfinite(area) & (area > 0)]
    return float(np.sqrt(np.median(area)))


def _with_polynomial(rect: ViewRectification, px: np.ndarray, degree: int) -> ViewRectification:
    """``rect`` with degree-``degree`` polynomials fitted to exact sample pairs, both directions."""
    r = rect.to_rectified(px)
    ok = np.isfinite(r).all(axis=1)
    if ok.sum() < (degree + 1) * (degree + 2) // 2:
        return rect
    W, H = rect.camera.width, rect.camera.height
    fwd = fit_polywarp(px[ok], r[ok], degree, (0.0, 0.0, float(W), float(H)))
    inv = fit_polywarp(r[ok], px[ok], degree)
    return dataclasses.replace(rect, polynomial=(fwd, inv))


def mesh_scale_m(camera: PinholeCamera, first_hit_m) -> float:
    """Ground sample distance (m per px) at the principal point from the coarse mesh's depth there
    (``first_hit_m`` as in ``facade_support``): the scale of a view that is not rectified; NaN where the
    ray misses the mesh."""
    o, d = camera.pixel_rays(np.array([camera.K[0, 2]]), np.array([camera.K[1, 2]]))
    t = float(np.asarray(first_hit_m(o, d), float)[0])
    if not np.isfinite(t):
        return float("nan")
    return t * float(d[0] @ camera.forward) / float(np.sqrt(camera.K[0, 0] * camera.K[1, 1]))


def frontal_footprint_m(cameras: list[PinholeCamera], first_hit_m) -> float:
    """The frontal views' footprint (m): the median over ``cameras`` of the width a view frames where its
    principal ray meets the coarse mesh (``mesh_scale_m`` times its width), views whose ray misses it left
    out; NaN where every one does. The unit of rectify's lengths: it follows the facade's scale (a model
    at 1:25 and the building it models, photographed alike, give 1:25), and within a building it is one
    length for every view."""
    widths = [mesh_scale_m(c, first_hit_m) * c.width for c in cameras]
    widths = [w for w in widths if np.isfinite(w)]
    return float(np.median(widths)) if widths else float("nan")


def remap_maps(rect: ViewRectification) -> tuple[np.ndarray, np.ndarray]:
    """``cv2.remap`` maps [height, width] float32 (OpenCV's integer pixel centres) of the rectified canvas."""
    ys, xs = np.mgrid[0 : rect.height, 0 : rect.width]
    src = rect.to_original(np.stack([xs.ravel() + 0.5, ys.ravel() + 0.5], axis=1)) - 0.5
    src = np.where(np.isfinite(src), src, -1e6)
    return (src[:, 0].reshape(rect.height, rect.width).astype(np.float32),
            src[:, 1].reshape(rect.height, rect.width).astype(np.float32))


def warp_image(image: np.ndarray, rect: ViewRectification) -> np.ndarray:
    """The rectified image [height, width, C] of ``image`` (bilinear; outside the original: black)."""
    if not rect.rectified:
        return image.copy()
    mx, my = remap_maps(rect)
    return cv2.remap(image, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def facade_support(rect: ViewRectification, first_hit_m, tolerance_m: float, step_px: int = 4) -> np.ndarray:
    """[height, width] bool of the rectified canvas: True where the facade surface is really there, i.e.
    the view's ray to the chart's point first meets the coarse mesh within ``tolerance_m`` of the surface
    (``first_hit_m(origins [N, 3], unit dirs [N, 3]) -> distances [N]``, inf: no hit). Beyond the facade's
    end the ray meets the ground, the sky or something else. Evaluated every ``step_px`` px and spread to
    the pixels around; all True for a view that is not rectified (no surface to compare with)."""
    if not rect.rectified:
        return np.ones((rect.height, rect.width), bool)
    ys, xs = np.mgrid[0 : rect.height : step_px, 0 : rect.width : step_px] + 0.5 * step_px
    m = rect.metres_per_px
    pts = rect.chart.point(rect.s0_m + xs.ravel() * m, rect.h0_m - ys.ravel() * m)
    d = pts - rect.camera.center
    dist = np.linalg.norm(d, axis=1)
    u = d / dist[:, None]
    t = np.asarray(first_hit_m(np.broadcast_to(rect.camera.center, d.shape), u), float)
    hit = rect.camera.center + np.where(np.isfinite(t), t, 0.0)[:, None] * u
    # distance of the hit from the surface, not along the ray: at grazing incidence a coarse mesh's bumps
    # move the hit far along the ray
    near = np.abs(rect.chart.surface().signed_distance(hit)) <= tolerance_m
    ok = (np.isfinite(t) & near).reshape(xs.shape).astype(np.uint8)
    return cv2.resize(ok, (rect.width, rect.height), interpolation=cv2.INTER_NEAREST).astype(bool)


def valid_region(rect: ViewRectification) -> np.ndarray:
    """[height, width] bool of the rectified canvas: True where the pixel shows the original view."""
    if not rect.rectified:
        return np.ones((rect.height, rect.width), bool)
    mx, my = remap_maps(rect)
    W, H = rect.camera.width, rect.camera.height
    return (mx >= 0) & (mx <= W - 1) & (my >= 0) & (my <= H - 1)
