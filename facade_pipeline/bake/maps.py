"""Baking the geometry prior of one view: world-space normal map and depth map by ray casting the
corrected mesh, and the facade and glass masks by projecting the 3D panels (the normal prior of Eq. 11);
and the ``06_bake_normals`` hand-off that holds it (``BakedPrior``: one writer, one reader).

Rays go through pixel centres (i + 0.5, j + 0.5), a chunk of rows at a time, so memory depends on the image
size and ``chunk_rays`` only. Normals are unit world vectors turned to face the camera (a camera inside or
behind the mesh sees back faces; their normals are flipped too); depth is along the camera z axis (m).
Pixels that hit nothing have ``valid`` False, a zero normal and zero depth: never NaN.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
import open3d as o3d

from facade_pipeline.errors import InputError
from facade_pipeline.geometry.camera import PinholeCamera
from facade_pipeline.geometry.raycast import MeshRaycaster
from facade_pipeline.io.exr import read_exr, write_exr
from facade_pipeline.io.images import read_mask, write_mask
from facade_pipeline.layout import BuildingLayout
from facade_pipeline.panels3d.model import PanelSet, PartSurface, part_outline

POLY_SHIFT = 4  # cv2 fixed-point bits: polygons are filled at 1/16 px
POLY_LIMIT_PX = 1 << 20  # projected polygon coordinates are clamped here (cv2 int32 fixed point)


INVALID_ID = np.iinfo(np.uint32).max  # open3d's primitive id of a ray that hit nothing


@dataclass(frozen=True, eq=False)
class BakedView:
    """``normal`` [H, W, 3] float32 (world, unit, facing the camera), ``depth`` [H, W] float32 (m, camera
    z), ``valid`` [H, W] bool, and ``label`` [H, W] uint8: the label of the hit triangle (0 where none)."""

    normal: np.ndarray
    depth: np.ndarray
    valid: np.ndarray
    label: np.ndarray


def facing_tables(
    rc: MeshRaycaster, center: np.ndarray, labels: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray]:
    """Per scene triangle, plus one last row for "no hit": the unit normal turned toward the camera centre
    ``center`` [3] (every ray from a pinhole meets a flat triangle from the same side, so the turn is a
    property of the triangle and the view, not of the pixel) [S + 1, 3] float32, and the triangle's label
    (``labels`` [F] of the caller's triangles, or 0) [S + 1] uint8. The last rows are zero."""
    away = np.einsum("ij,ij->i", rc.tri_vertex - center, rc.tri_normals) > 0
    normals = np.zeros((len(rc.prim_map) + 1, 3), np.float32)
    normals[:-1] = np.where(away[:, None], -rc.tri_normals, rc.tri_normals)
    lab = np.zeros(len(rc.prim_map) + 1, np.uint8)
    if labels is not None:
        lab[:-1] = np.asarray(labels, np.uint8)[rc.prim_map]
    return normals, lab


def bake_view(
    rc: MeshRaycaster,
    camera: PinholeCamera,
    chunk_rays: int,
    progress: Callable[[int], None] | None = None,
    labels: np.ndarray | None = None,
) -> BakedView:
    """Ray-cast every pixel of ``camera`` against the mesh of ``rc``, in bands of whole rows of about
    ``chunk_rays`` rays; ``labels`` [F] (uint8, one per triangle of the caller's mesh) gives each hit
    pixel its triangle's label. Rays are built by open3d (float32) through pixel centres with camera-z
    component 1, so the hit distance is the depth along the camera axis. Only the hit distance and the
    triangle id are read per ray; normals and labels are looked up by id in per-view tables."""
    h, w = camera.height, camera.width
    normal = np.zeros((h, w, 3), np.float32)
    depth = np.zeros((h, w), np.float32)
    valid = np.zeros((h, w), bool)
    label = np.zeros((h, w), np.uint8)
    band = max(1, int(chunk_rays) // max(1, w))
    extrinsic = o3d.core.Tensor(camera.cam_from_world)
    normals_t, labels_t = facing_tables(rc, camera.center, labels)
    last = len(rc.prim_map)
    for r0 in range(0, h, band):
        rows = min(band, h - r0)
        if not rc.empty:
            K = camera.K.copy()
            K[1, 2] -= r0  # the band's first row becomes row 0
            rays = o3d.t.geometry.RaycastingScene.create_rays_pinhole(o3d.core.Tensor(K), extrinsic, w, rows)
            out = rc.scene.cast_rays(rays)
            ids = out["primitive_ids"].numpy().reshape(rows, w)
            hit = ids != INVALID_ID
            idx = np.minimum(ids, last)  # misses -> the zero row
            valid[r0 : r0 + rows] = hit
            np.copyto(depth[r0 : r0 + rows], out["t_hit"].numpy().reshape(rows, w), where=hit)
            np.take(normals_t, idx, axis=0, out=normal[r0 : r0 + rows])
            if labels is not None:
                np.take(labels_t, idx, out=label[r0 : r0 + rows])
        if progress is not None:
            progress(rows * w)
    return BakedView(normal, depth, valid, label)


def _outline(surface: PartSurface, szh: np.ndarray, samples: int) -> np.ndarray:
    """World points [4 * samples, 3] around the (s, z) rectangle-like outline ``szh`` [4, 3] on the
    surface (edges sampled so that curved edges stay curved)."""
    u = np.linspace(0.0, 1.0, samples, endpoint=False)[:, None]
    edges = [szh[k] + u * (szh[(k + 1) % 4] - szh[k]) for k in range(4)]
    return surface.points(np.concatenate(edges))


def fill_polygon(camera: PinholeCamera, world: np.ndarray, near_m: float, out: np.ndarray) -> None:
    """Set to True the pixels of ``out`` [H, W] whose centres lie inside the image of the planar-ish
    polygon ``world`` [M, 3], clipped at ``near_m`` (m) in front of the camera."""
    pc = camera.world_to_cam(world)
    pc = _clip_near(pc, near_m)
    if len(pc) < 3:
        return
    uv = (pc @ camera.K.T)[:, :2] / pc[:, 2:3]
    uv = np.clip(uv - 0.5, -POLY_LIMIT_PX, POLY_LIMIT_PX)
    pts = np.round(uv * (1 << POLY_SHIFT)).astype(np.int32).reshape(-1, 1, 2)
    tmp = np.zeros(out.shape, np.uint8)
    cv2.fillPoly(tmp, [pts], 1, lineType=cv2.LINE_8, shift=POLY_SHIFT)
    out |= tmp.astype(bool)


def _clip_near(pc: np.ndarray, near: float) -> np.ndarray:
    """Sutherland-Hodgman clipping of a polygon [M, 3] (camera frame) to the half space z >= near."""
    out = []
    for k in range(len(pc)):
        a, b = pc[k], pc[(k + 1) % len(pc)]
        if a[2] >= near:
            out.append(a)
        if (a[2] >= near) != (b[2] >= near):
            t = (near - a[2]) / (b[2] - a[2])
            out.append(a + t * (b - a))
    return np.array(out).reshape(-1, 3)


def panel_masks(
    panels: PanelSet, camera: PinholeCamera, edge_samples: int, near_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """(facade, glass) masks [H, W] bool of the view: the projected parts (panels and frames around them)
    and the projected panels."""
    facade = np.zeros((camera.height, camera.width), bool)
    glass = np.zeros_like(facade)
    for k, surface in enumerate(panels.parts):
        own = panels.of_part(k)
        if not own:
            continue
        fill_polygon(camera, _outline(surface, part_outline(own, surface), edge_samples), near_m, facade)
        for p in own:
            fill_polygon(camera, _outline(surface, surface.coords(p.corners), edge_samples), near_m, glass)
    return facade | glass, glass


BakedMap = Literal["normal_map", "depth_map", "facade_mask", "glass_mask"]
#: the files of one view in 06_bake_normals (layout keys ``bake_<map>``), in the order they are written
BAKED_MAPS: tuple[BakedMap, ...] = ("normal_map", "depth_map", "facade_mask", "glass_mask")


@dataclass(frozen=True, eq=False)
class BakedPrior:
    """The ``06_bake_normals`` hand-off of one UAV view (data_layout.md): ``normal`` [H, W, 3] float32
    (world, unit, facing the camera, zero where not ``valid``), ``valid`` [H, W] bool, ``depth`` [H, W]
    float32 (m along the camera z axis, zero where not valid), the ``facade`` and ``glass`` masks [H, W]
    bool. ``save`` is the one writer and ``load`` the one reader; a reader that needs only some maps
    (the masks, say) loads those, and the others are None, as in a stand-in that writes only some."""

    stem: str
    normal: np.ndarray | None = None
    valid: np.ndarray | None = None
    depth: np.ndarray | None = None
    facade: np.ndarray | None = None
    glass: np.ndarray | None = None

    @staticmethod
    def paths(layout: BuildingLayout, stem: str, maps: tuple[BakedMap, ...] = BAKED_MAPS) -> dict[str, Path]:
        """The files of ``maps`` of view ``stem``, by map name."""
        return {m: layout.path(f"bake_{m}", stem=stem) for m in maps}

    def save(self, layout: BuildingLayout) -> list[Path]:
        """Write the maps that are set (atomically, each EXR with its ``valid`` channel); returns their
        paths."""
        out = self.paths(layout, self.stem)
        valid = None if self.valid is None else self.valid.astype(np.float32)
        written = []
        for name, channels in (
            ("normal_map", None if self.normal is None else {"N": self.normal, "valid": valid}),
            ("depth_map", None if self.depth is None else {"depth": self.depth, "valid": valid}),
        ):
            if channels is not None:
                assert valid is not None, f"{self.stem}: {name} without its valid mask"
                write_exr(out[name], channels)
                written.append(out[name])
        for name, mask in (("facade_mask", self.facade), ("glass_mask", self.glass)):
            if mask is not None:
                write_mask(out[name], mask)
                written.append(out[name])
        return written

    @classmethod
    def load(
        cls,
        layout: BuildingLayout,
        stem: str,
        shape: tuple[int, int] | None,
        maps: tuple[BakedMap, ...] = BAKED_MAPS,
    ) -> BakedPrior:
        """Read ``maps`` of view ``stem``, each checked to be ``shape`` (H, W: the view's camera) unless
        None; the EXRs must have their channels, and both EXRs the same ``valid``."""
        paths = cls.paths(layout, stem, maps)
        got: dict[str, np.ndarray] = {}
        for name, channel in (("normal_map", "N"), ("depth_map", "depth")):
            if name not in maps:
                continue
            exr = read_exr(paths[name])
            if channel not in exr or "valid" not in exr:
                axes = ".X/Y/Z" if channel == "N" else ""
                raise InputError(
                    paths[name], f"channels {channel}{axes} and valid", f"channels {sorted(exr)}"
                )
            hw = shape or exr["valid"].shape[:2]
            got[channel] = _checked(paths[name], exr[channel], (*hw, 3) if channel == "N" else hw)
            valid = _checked(paths[name], exr["valid"], hw) > 0.5
            if "valid" in got and not np.array_equal(got["valid"], valid):
                raise InputError(paths[name], f"the valid channel of {paths['normal_map'].name}", "another")
            got["valid"] = valid
        for name in ("facade_mask", "glass_mask"):
            if name in maps:
                mask = read_mask(paths[name])
                got[name] = mask if shape is None else _checked(paths[name], mask, shape)
        return cls(
            stem,
            got.get("N"),
            got.get("valid"),
            got.get("depth"),
            got.get("facade_mask"),
            got.get("glass_mask"),
        )


def _checked(path: Path, arr: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    if arr.shape != shape:
        raise InputError(path, f"a map of shape {shape} (the view's camera)", f"shape {arr.shape}")
    return arr
