"""Stage ``import_photogrammetry``: bring a photogrammetry project into the pipeline's local frame.

Reads ``raw/`` (COLMAP model(s), images, coarse mesh, coarse point cloud), checks every file, undistorts
images whose camera has distortion (pycolmap), moves georeferenced coordinates to a local z-up origin and
writes the normalised scene into ``01_import/``. Nothing under ``raw/`` is modified.
"""

from __future__ import annotations

import logging
import sys
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import TYPE_CHECKING, Annotated, Literal

import numpy as np
from tqdm import tqdm

from facade_pipeline.config import Fraction, NonNeg, Range, RunSettings
from facade_pipeline.errors import InputError
from facade_pipeline.geometry.frames import (
    AXES,
    estimate_up_from_cameras,
    invert_rigid,
    local_from_model,
    transform_points,
)
from facade_pipeline.layout import BuildingLayout
from facade_pipeline.scene import ImportedScene, Role, View
from stages._runner import StageReport, main

if TYPE_CHECKING:  # names for annotations only: the functions that use them import them
    import pycolmap

    from facade_pipeline.importing.checks import SceneCheck
    from facade_pipeline.io import colmap

log = logging.getLogger(__name__)
NAME = "import_photogrammetry"
DOC = "import the COLMAP model, images, coarse mesh and points into a local z-up frame, undistorted"
UPSTREAM: tuple[str, ...] = ()
#: a model with a coordinate beyond this (m) is georeferenced (UTM: z up, far from the origin). UTM
#: eastings are above 1.6 x 10^5 m and northings above 0 only near the equator; a model in its own
#: photogrammetric frame spans hundreds of metres at most: 10 km separates the two with room either way
GEOREF_THRESHOLD_M = 10_000.0
#: an up direction estimated from the cameras within this angle (deg) of a model axis is snapped to it
AUTO_UP_SNAP_DEG = 15.0


@dataclass(frozen=True)
class Params:
    up_axis: Literal["auto", "+x", "-x", "+y", "-y", "+z", "-z"]
    """World up in the raw model; ``auto`` uses z for georeferenced models, else the camera orientations."""
    recenter: Literal["auto", "always", "never"]
    """Move to a local origin: ``auto`` for georeferenced models only."""
    origin_rounding_m: NonNeg
    """The local origin is rounded to a multiple of this (m)."""
    max_size_ratio: Annotated[float, Range(1.0)]
    """The coarse mesh's size may differ from the camera layout's by at most this factor (a unit error)."""
    min_views_seeing_mesh: Fraction
    """At least this share of the UAV views must have rays that meet the coarse mesh (0: no check)."""


@dataclass(frozen=True)
class _Source:
    """One COLMAP model of ``raw/`` with its image folder and role."""

    role: Role
    model_dir: Path
    image_dir: Path


def _sources(layout: BuildingLayout) -> list[_Source]:
    sources = [_Source("uav", layout.raw_sparse_dir, layout.raw_images_dir)]
    if layout.raw_frontal_images_dir.exists() or layout.raw_frontal_sparse_dir.exists():
        sources.append(_Source("frontal", layout.raw_frontal_sparse_dir, layout.raw_frontal_images_dir))
    return sources


def _model_files(model_dir: Path) -> list[Path]:
    return sorted(p for p in model_dir.iterdir() if p.is_file() and p.suffix in (".bin", ".txt"))


def _coarse_mesh_path(layout: BuildingLayout) -> Path:
    found = [p for p in layout.raw_coarse_mesh_candidates if p.is_file()]
    if len(found) != 1:
        ply, obj = layout.raw_coarse_mesh_candidates
        raise InputError(
            layout.raw_dir,
            f"exactly one coarse mesh ({ply.name} or {obj.name})",
            f"{len(found)} ({', '.join(p.name for p in found) or 'none'})",
        )
    return found[0]


def _checked_name(name: str, src: _Source) -> str:
    """An image name of a COLMAP model, checked to stay inside the model's image folder."""
    p = PurePosixPath(name)
    if not name or p.is_absolute() or ".." in p.parts or "\\" in name:
        raise InputError(
            src.model_dir,
            f"image names relative to {src.image_dir}, without '..' or a leading '/'",
            f"{name!r}: rename the image in the model",
        )
    return name


def inputs(layout: BuildingLayout, params: Params) -> list[Path]:
    """Every raw file the stage reads, after checking the models, images and sizes."""
    # imported here, not at the top: doit loads every stage module to build its task list
    from facade_pipeline.io import colmap
    from facade_pipeline.io.images import image_size

    if not layout.raw_dir.is_dir():
        raise InputError(layout.raw_dir, "the folder of raw data (see data_layout.md)", "no folder")
    files: list[Path] = []
    for src in _sources(layout):
        rec = colmap.read_reconstruction(src.model_dir)
        files += _model_files(src.model_dir)
        stems: dict[str, str] = {}
        for im in colmap.registered_images(rec):
            path = src.image_dir / _checked_name(im.name, src)
            stem = str(PurePosixPath(im.name).with_suffix(""))
            if stem in stems:
                raise InputError(
                    src.image_dir,
                    "one image per name without extension (outputs are named by it)",
                    f"{stems[stem]} and {im.name}: rename one and its entry in {src.model_dir}",
                )
            stems[stem] = im.name
            cam = im.camera
            colmap.check_camera_supported(cam, src.model_dir)
            pose = im.cam_from_world().matrix()
            if not (np.isfinite(pose).all() and np.isfinite(cam.params).all()):
                raise InputError(
                    src.model_dir,
                    f"a finite pose and camera for image {im.name}",
                    "NaN or Inf: re-export the model, or remove the image from it",
                )
            w, h = image_size(path)
            if (w, h) != (cam.width, cam.height):
                raise InputError(
                    path,
                    f"{cam.width}x{cam.height} pixels (camera {cam.camera_id} in {src.model_dir})",
                    f"{w}x{h}",
                )
            files.append(path)
    files.append(_coarse_mesh_path(layout))
    if layout.raw_coarse_points.is_file():
        files.append(layout.raw_coarse_points)
    return files


def _local_frame(
    rec: pycolmap.Reconstruction, mesh_vertices: np.ndarray, params: Params
) -> tuple[np.ndarray, str]:
    """``local_from_model`` [4, 4] and how up was found."""
    # imported here, not at the top: doit loads every stage module to build its task list
    from facade_pipeline.io import colmap

    centres = np.array([im.projection_center() for im in colmap.registered_images(rec)])
    extent = max(np.abs(centres).max(), np.abs(mesh_vertices).max())
    georeferenced = extent > GEOREF_THRESHOLD_M
    if params.up_axis != "auto":
        up, method = np.array(AXES[params.up_axis]), f"configured ({params.up_axis})"
    elif georeferenced:
        up, method = np.array(AXES["+z"]), "georeferenced model (z up)"
    else:
        R = np.array([im.cam_from_world().rotation.matrix() for im in colmap.registered_images(rec)])
        est = estimate_up_from_cameras(R, AUTO_UP_SNAP_DEG)
        up, method = est.up, est.method
    recenter = params.recenter == "always" or (params.recenter == "auto" and georeferenced)
    T = local_from_model(up, centres.mean(axis=0), recenter, params.origin_rounding_m)
    return T, method


def _import_views(
    src: _Source, rec: pycolmap.Reconstruction, layout: BuildingLayout, params: Params, bar: tqdm
) -> tuple[list[View], list[colmap.ColmapView]]:
    # imported here, not at the top: doit loads every stage module to build its task list
    from facade_pipeline.io import colmap
    from facade_pipeline.io.images import read_image, write_image

    opts = colmap.undistort_options()
    pinhole: dict[int, pycolmap.Camera] = {}
    views, model_views = [], []
    for im in colmap.registered_images(rec):
        cam = im.camera
        if cam.camera_id not in pinhole:
            pinhole[cam.camera_id] = colmap.undistort_camera(opts, cam)
        stem = str(PurePosixPath(im.name).with_suffix(""))
        out = layout.import_image(stem) if src.role == "uav" else layout.import_frontal_image(stem)
        rgb = colmap.undistort_rgb(opts, read_image(src.image_dir / im.name), cam)
        write_image(out, rgb)
        camera = colmap.pinhole_camera(pinhole[cam.camera_id], im.cam_from_world())
        views.append(View(im.name, stem, src.role, camera, layout.relative(out)))
        model_views.append(colmap.ColmapView(f"{stem}.png", camera))
        bar.update(1)
    return views, model_views


def _check_scene(layout: BuildingLayout, params: Params, views: list[View], mesh) -> SceneCheck:
    """The cameras and the coarse mesh in one frame and one unit, or one line saying which is off."""
    # imported here, not at the top: doit loads every stage module to build its task list
    from facade_pipeline.importing.checks import check_scene, units_hint

    mesh_path = _coarse_mesh_path(layout)
    cams = {f"{v.role}:{v.stem}": v.camera for v in views}
    uav = [k for k in cams if k.startswith("uav:")]
    check = check_scene(cams, np.asarray(mesh.vertices), np.asarray(mesh.triangles), uav)
    ratio, limit = check.size_ratio, params.max_size_ratio
    units_off = not 1 / limit <= ratio <= limit
    share = check.share_seeing(uav)
    if share < params.min_views_seeing_mesh:
        raise InputError(
            mesh_path,
            f"a coarse mesh the UAV cameras see (rays of at least {params.min_views_seeing_mesh:.0%} of the "
            "views meet it: import_photogrammetry.min_views_seeing_mesh)",
            f"{share:.0%} of {len(uav)} views: is it in the world frame of "
            f"{layout.relative(layout.raw_sparse_dir)} (same origin, axes and scale)?"
            + (f" And {units_hint(ratio)}" if units_off else ""),
        )
    if units_off:
        raise InputError(
            mesh_path,
            f"a coarse mesh in the units of {layout.relative(layout.raw_sparse_dir)} (its size within "
            f"{limit:g}x of the camera layout's: import_photogrammetry.max_size_ratio)",
            units_hint(ratio),
        )
    frontal = [k for k in cams if k.startswith("frontal:")]
    blind = [k.split(":", 1)[1] for k in frontal if check.seeing[k] == 0]
    if frontal and len(blind) == len(frontal):
        raise InputError(
            layout.raw_frontal_sparse_dir,
            "frontal views in the world frame of the UAV model (their rays meet the coarse mesh)",
            f"none of {len(frontal)} frontal views sees the coarse mesh: register the frontal images "
            "together with the UAV images (one COLMAP run) or align the two models",
        )
    if blind:
        log.warning(
            "%d of %d frontal views do not see the coarse mesh (%s): they will be skipped; check their poses",
            len(blind), len(frontal), ", ".join(blind[:5]) + (" ..." if len(blind) > 5 else ""),
        )  # fmt: skip
    return check


def run(layout: BuildingLayout, params: Params, settings: RunSettings) -> StageReport:
    # imported here, not at the top: doit loads every stage module to build its task list
    import pycolmap

    from facade_pipeline.io import colmap
    from facade_pipeline.io.meshes import make_points, read_mesh, read_points, write_mesh, write_points
    from facade_pipeline.meshing.clean import clean_mesh

    sources = _sources(layout)
    recs = [colmap.read_reconstruction(s.model_dir) for s in sources]
    mesh, cleaned = clean_mesh(read_mesh(_coarse_mesh_path(layout)))
    T, up_method = _local_frame(recs[0], np.asarray(mesh.vertices), params)
    sim = pycolmap.Sim3d(1.0, pycolmap.Rotation3d(T[:3, :3]), T[:3, 3].copy())
    for rec in recs:
        rec.transform(sim)  # local_from_model applied to poses and points, in float64

    outputs: list[Path] = []
    views: list[View] = []
    n_total = sum(r.num_reg_images() for r in recs)
    with tqdm(total=n_total, desc="import: undistort images", unit="img", file=sys.stderr) as bar:
        for src, rec in zip(sources, recs, strict=True):
            v, model_views = _import_views(src, rec, layout, params, bar)
            views += v
            sparse_out = layout.import_sparse_dir if src.role == "uav" else layout.import_frontal_sparse_dir
            xyz = np.array([p.xyz for p in rec.points3D.values()]).reshape(-1, 3)
            rgb = np.array([p.color for p in rec.points3D.values()], dtype=np.uint8).reshape(-1, 3)
            colmap.write_pinhole_model(sparse_out, model_views, xyz, rgb)
            outputs += _model_files(sparse_out)
    outputs += [layout.root / v.image for v in views]

    mesh.vertices = type(mesh.vertices)(transform_points(T, np.asarray(mesh.vertices)))
    check = _check_scene(layout, params, views, mesh)
    mesh.compute_vertex_normals()
    write_mesh(layout.import_coarse_mesh, mesh)
    if layout.raw_coarse_points.is_file():
        pcd, points_source = read_points(layout.raw_coarse_points), "raw/coarse_points.ply"
        pcd.points = type(pcd.points)(transform_points(T, np.asarray(pcd.points)))
    else:
        pts = recs[0].points3D.values()
        if not pts:
            raise InputError(
                layout.raw_coarse_points, "a coarse point cloud, or points in raw/sparse/0", "neither"
            )
        pcd = make_points(np.array([p.xyz for p in pts]), np.array([p.color for p in pts]) / 255.0)
        points_source = "raw/sparse/0 points3D"
    write_points(layout.import_coarse_points, pcd)

    georef_from_local = invert_rigid(T)
    ImportedScene(tuple(views), georef_from_local, up_method, points_source).save(layout.import_scene)
    outputs += [layout.import_coarse_mesh, layout.import_coarse_points, layout.import_scene]
    n_undistorted = sum(not colmap.is_pinhole(im.camera) for r in recs for im in colmap.registered_images(r))
    return StageReport(
        outputs,
        {
            "n_uav_images": sum(v.role == "uav" for v in views),
            "n_frontal_images": sum(v.role == "frontal" for v in views),
            "n_undistorted_images": n_undistorted,
            "up_axis_method": up_method,
            "georef_offset_m": georef_from_local[:3, 3].tolist(),
            "coarse_mesh_vertices": len(mesh.vertices),
            "coarse_mesh_triangles": len(mesh.triangles),
            "coarse_mesh_cleaned": cleaned,
            "coarse_points": len(pcd.points),
            "points_source": points_source,
            "mesh_size_ratio": round(check.size_ratio, 3),
            "uav_views_seeing_mesh": check.share_seeing([f"uav:{v.stem}" for v in views if v.role == "uav"]),
            "frontal_views_seeing_mesh": check.share_seeing(
                [f"frontal:{v.stem}" for v in views if v.role == "frontal"]
            ),
        },
    )


def targets(layout: BuildingLayout, params: Params) -> list[Path]:
    return [layout.import_scene, layout.import_coarse_mesh, layout.import_coarse_points]


if __name__ == "__main__":
    raise SystemExit(main(sys.modules[__name__]))
