"""Rectification of a frontal view of a curved facade into a planar-facade image (paper, 3.1.1, Fig. 3).

Given the view's pinhole camera and the fitted surface (``cylinder.Surface``):

1. the patch: rays through an ``n x n`` grid of image positions spanning the whole image, borders included,
   hit the surface at the "green" points X_g (world, m); the image borders bound the patch;
2. the tangent plane at the patch's angular centre phi_c = (phi_min + phi_max) / 2 (phi about the axis);
3. the "blue" points X_b = X_g - ((X_g - P_c) . n_c) n_c, the orthogonal projection onto that plane;
4. both sets projected into the image (Eq. 6) give pixel pairs (g, b); the rectified image's pixel of g is
   r = b - o, with o the corner of the blue points' bounding box (the rectified canvas holds all of them);
5. degree-7 polynomial warps (``polywarp``) r = F(g) (forward: original -> rectified) and g = G(r)
   (inverse: rectified -> original), fitted in both directions; ``cv2.remap`` with G builds the image.

When every blue point lies within ``planar_shift_px`` of its green point the surface is flat over the patch:
the view passes through with identity warps and the image unchanged.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import cv2
import numpy as np

from facade_pipeline.errors import InputError
from facade_pipeline.geometry.camera import PinholeCamera
from facade_pipeline.geometry.cylinder import Surface
from facade_pipeline.geometry.polywarp import PolyWarp, fit_polywarp
from facade_pipeline.io.atomic import write_json

Kind = Literal["curved", "planar", "no_surface"]


@dataclass(frozen=True)
class RectifyParams:
    samples_per_side: int
    """Patch samples along each image side (-); the grid includes the image borders."""
    degree: int
    """Total degree of the polynomial warps (-); the paper uses 7."""
    planar_shift_px: float
    """Largest green-to-blue shift (px) under which the patch counts as flat: identity warps."""


@dataclass(frozen=True, eq=False)
class ViewRectification:
    """The hand-off of ``rectify`` for one frontal view: warps between the original image (W x H) and the
    rectified canvas (width x height), both in pixels with centres at (i + 0.5, j + 0.5)."""

    kind: Kind
    width: int  # rectified canvas (px)
    height: int
    forward: PolyWarp  # original -> rectified
    inverse: PolyWarp  # rectified -> original
    max_shift_px: float  # largest green-to-blue shift on the samples

    def to_dict(self) -> dict:
        return {"kind": self.kind, "rectified_width": self.width, "rectified_height": self.height,
                "max_shift_px": self.max_shift_px, "forward": self.forward.to_dict(),
                "inverse": self.inverse.to_dict()}

    def save(self, path: str | Path) -> None:
        write_json(path, self.to_dict())

    @classmethod
    def load(cls, path: str | Path) -> ViewRectification:
        try:
            d = json.loads(Path(path).read_text())
            return cls(d["kind"], int(d["rectified_width"]), int(d["rectified_height"]),
                       PolyWarp.from_dict(d["forward"]), PolyWarp.from_dict(d["inverse"]),
                       float(d["max_shift_px"]))
        except (OSError, json.JSONDecodeError, KeyError, TypeError, ValueError) as e:
            raise InputError(path, "a rectification (JSON with kind, sizes, forward and inverse warps)",
                             f"{type(e).__name__}: {e}") from None

    @classmethod
    def identity(cls, width: int, height: int, kind: Kind, max_shift_px: float = 0.0) -> ViewRectification:
        warp = PolyWarp.identity((0.0, 0.0, float(width), float(height)))
        return cls(kind, width, height, warp, warp, max_shift_px)


def image_grid(width: int, height: int, n: int) -> np.ndarray:
    """[n * n, 2] positions on a regular grid spanning [0, W] x [0, H], borders included (px)."""
    xs, ys = np.meshgrid(np.linspace(0.0, width, n), np.linspace(0.0, height, n))
    return np.stack([xs.ravel(), ys.ravel()], axis=1)


def patch_points(surface: Surface, camera: PinholeCamera,
                 pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Green points: the surface hit by the rays through ``pixels`` [N, 2]. Returns (pixels, points) [M, ...]
    of the rays that hit."""
    o, d = camera.pixel_rays(pixels[:, 0], pixels[:, 1])
    lam = surface.intersect(o, d)
    hit = np.isfinite(lam)
    return pixels[hit], o[hit] + lam[hit, None] * d[hit]


def tangent_plane(surface: Surface, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Point [3] and unit normal [3] of the plane tangent to ``surface`` at the angular centre of
    ``points`` [N, 3]."""
    k = surface.curvature_per_m
    if k == 0.0:
        return surface.origin, surface.normal
    t, w = surface.local(points)
    # angle about the axis, measured from p0; the sign of kappa keeps it near 0 for concave surfaces too
    phi = np.arctan2(k * t, 1.0 + k * w)
    phi_c = 0.5 * (phi.min() + phi.max())
    radial = np.cos(phi_c) * surface.normal + np.sin(phi_c) * surface.binormal
    centre = surface.origin - surface.normal / k
    return centre + radial / k, radial


def rectify_view(camera: PinholeCamera, surface: Surface, params: RectifyParams) -> ViewRectification:
    """The warps of one view (steps 1-5 of the module docstring); identity when the patch is flat."""
    W, H = camera.width, camera.height
    green_px, green = patch_points(surface, camera, image_grid(W, H, params.samples_per_side))
    n_terms = (params.degree + 1) * (params.degree + 2) // 2
    if len(green) < n_terms:
        return ViewRectification.identity(W, H, "no_surface")
    p_c, n_c = tangent_plane(surface, green)
    blue = green - ((green - p_c) @ n_c)[:, None] * n_c
    blue_px, z = camera.project(blue)
    shift = float(np.nanmax(np.linalg.norm(blue_px - green_px, axis=1))) if np.all(z > 0) else np.inf
    if shift <= params.planar_shift_px:
        return ViewRectification.identity(W, H, "planar", shift)
    lo = np.floor(blue_px.min(axis=0))
    size = np.ceil(blue_px.max(axis=0) - lo).astype(int)
    rect_px = blue_px - lo
    forward = fit_polywarp(green_px, rect_px, params.degree, (0.0, 0.0, float(W), float(H)))
    inverse = fit_polywarp(rect_px, green_px, params.degree, (0.0, 0.0, float(size[0]), float(size[1])))
    return ViewRectification("curved", int(size[0]), int(size[1]), forward, inverse, shift)


def remap_maps(warp: PolyWarp, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """``cv2.remap`` maps [H, W] float32 (OpenCV's integer pixel centres) of ``warp`` over a W x H canvas."""
    ys, xs = np.mgrid[0:height, 0:width]
    src = warp(np.stack([xs.ravel() + 0.5, ys.ravel() + 0.5], axis=1)) - 0.5
    return (src[:, 0].reshape(height, width).astype(np.float32),
            src[:, 1].reshape(height, width).astype(np.float32))


def warp_image(image: np.ndarray, rect: ViewRectification) -> np.ndarray:
    """The rectified image [height, width, C] of ``image`` (bilinear; outside the original: black)."""
    if rect.kind != "curved":
        return image.copy()
    mx, my = remap_maps(rect.inverse, rect.width, rect.height)
    return cv2.remap(image, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def valid_region(rect: ViewRectification, width: int, height: int) -> np.ndarray:
    """[height, width] bool of the rectified canvas: True where the inverse warp lands inside the
    original W x H view (all True for identity warps)."""
    if rect.kind != "curved":
        return np.ones((rect.height, rect.width), bool)
    mx, my = remap_maps(rect.inverse, rect.width, rect.height)
    return (mx >= 0) & (mx <= width - 1) & (my >= 0) & (my <= height - 1)
