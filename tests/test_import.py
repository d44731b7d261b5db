"""The import_photogrammetry stage on pycolmap's synthetic reconstructions and hand-made meshes."""

from __future__ import annotations

import dataclasses
import json

import cv2
import numpy as np
import pycolmap
import pytest

from facade_pipeline.config import default_params
from facade_pipeline.errors import InputError
from facade_pipeline.geometry.frames import transform_points
from facade_pipeline.io.images import write_image
from facade_pipeline.io.meshes import make_mesh, read_mesh, write_mesh
from facade_pipeline.scene import ImportedScene
from stages import import_photogrammetry as stage
from stages._runner import execute
from tests.helpers import make_raw, synthetic_reconstruction, tree_digest

PARAMS = default_params(stage.NAME, stage.Params)


def test_import_writes_scene_and_keeps_raw_untouched(layout):
    rec = make_raw(layout, frontal=True)
    before = tree_digest(layout.raw_dir)
    manifest = execute(stage, layout, PARAMS)
    assert tree_digest(layout.raw_dir) == before
    scene = ImportedScene.load(layout)
    assert len(scene.uav_views) == rec.num_reg_images() == len(scene.frontal_views)
    for v in scene.views:
        img = cv2.imread(str(layout.root / v.image))
        assert img.shape[:2] == (v.camera.height, v.camera.width)
    assert manifest["metrics"]["n_undistorted_images"] == 2 * rec.num_reg_images()
    assert set(manifest["outputs"]) >= {
        "01_import/scene.json",
        "01_import/coarse_mesh.ply",
        "01_import/coarse_points.ply",
        "01_import/sparse/0/cameras.bin",
    }
    # the normalised model is a pinhole COLMAP model that pycolmap reads back
    out = pycolmap.Reconstruction(str(layout.import_sparse_dir))
    assert {c.model.name for c in out.cameras.values()} == {"PINHOLE"}
    assert json.loads(layout.manifest(stage.NAME).read_text())["inputs"]


def test_georeferenced_round_trip_under_1mm(layout):
    offset = (734512.25, 2483915.75, 41.5)  # UTM zone 50Q, around Hong Kong: 10^6 m
    rec = make_raw(layout, offset=offset)
    execute(stage, layout, PARAMS)
    scene = ImportedScene.load(layout)
    G = scene.georef_from_local
    assert np.allclose(G[:3, :3], np.eye(3)) and np.abs(G[:3, 3]).min() > 40  # z up kept, origin moved
    centres = {im.name: im.projection_center() for im in rec.images.values()}
    local = np.array([v.camera.center for v in scene.uav_views])
    assert np.abs(local).max() < 10.0  # near the origin now
    back = transform_points(G, local)
    err = np.abs(back - np.array([centres[v.name] for v in scene.uav_views])).max()
    assert err < 1e-3
    raw_mesh = np.asarray(read_mesh(layout.raw_coarse_mesh_candidates[0]).vertices)
    mesh_back = transform_points(G, np.asarray(read_mesh(layout.import_coarse_mesh).vertices))
    assert np.abs(mesh_back - raw_mesh).max() < 1e-3


def _blob_image(h, w, centres, sigma=2.0):
    yy, xx = np.mgrid[0:h, 0:w] + 0.5  # pixel centres at +0.5
    img = np.zeros((h, w))
    for cx, cy in centres:
        img += np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * sigma**2))
    return img


def test_undistortion_reprojects_known_points_within_0_1px(layout):
    w, h = 320, 240
    rec = synthetic_reconstruction(
        n_images=6,
        width=w,
        height=h,
        model="OPENCV",
        params=(260.0, 255.0, 161.0, 119.0, -0.12, 0.03, 0.001, -0.0015),
    )
    make_raw(layout, rec=rec)
    # redraw each image: Gaussian blobs where known 3D points land through the distorted camera
    pts = np.array([p.xyz for p in rec.points3D.values()])
    for im in rec.images.values():
        uv = np.array([im.project_point(p) for p in pts if im.project_point(p) is not None])
        inside = (uv[:, 0] > 12) & (uv[:, 0] < w - 12) & (uv[:, 1] > 12) & (uv[:, 1] < h - 12)
        img = _blob_image(h, w, uv[inside])
        write_image(
            layout.raw_image(im.name),
            np.repeat((np.clip(img, 0, 1) * 255).round().astype(np.uint8)[..., None], 3, 2),
        )
    execute(stage, layout, PARAMS)
    scene = ImportedScene.load(layout)
    pts_local = transform_points(np.linalg.inv(scene.georef_from_local), pts)
    errors = []
    for v in scene.uav_views:
        rgb = cv2.imread(str(layout.root / v.image))[..., 0].astype(np.float64) / 255.0
        uv, z = v.camera.project(pts_local)
        uv = uv[z > 0]
        dist = np.linalg.norm(uv[:, None] - uv[None], axis=-1) + np.eye(len(uv)) * 1e9
        for x, y in uv[dist.min(axis=1) > 16]:  # isolated blobs only: neighbours would bias the centroid
            if not (15 < x < v.camera.width - 15 and 15 < y < v.camera.height - 15):
                continue
            x0, y0 = int(x), int(y)
            win = rgb[y0 - 6 : y0 + 7, x0 - 6 : x0 + 7]
            if win.sum() < 1.0 or win.max() < 0.5:
                continue  # the blob was outside the distorted image
            yy, xx = np.mgrid[y0 - 6 : y0 + 7, x0 - 6 : x0 + 7] + 0.5
            cx, cy = (win * xx).sum() / win.sum(), (win * yy).sum() / win.sum()
            errors.append(np.hypot(cx - x, cy - y))
    assert len(errors) >= 8
    assert np.median(errors) < 0.1 and np.max(errors) < 0.25, (np.median(errors), np.max(errors))


# --- bad input: one clear error naming the file ---


def _corrupt(layout):
    (layout.raw_sparse_dir / "images.bin").write_bytes(b"\x07\x00\x00\x00garbage")


def _cut_short(name, keep=None):
    def damage(layout):
        path = layout.raw_sparse_dir / name
        data = path.read_bytes()
        path.write_bytes(data[: len(data) - 10 if keep is None else keep])

    return damage


def _truncated_mesh(layout):
    p = layout.raw_coarse_mesh_candidates[0]
    data = p.read_bytes()
    p.write_bytes(data[: len(data) * 2 // 3])


def _missing_image(layout):
    next(layout.raw_images_dir.iterdir()).unlink()


def _wrong_size(layout):
    p = next(layout.raw_images_dir.iterdir())
    write_image(p, np.zeros((10, 12, 3), np.uint8))


def _no_faces(layout):
    p = layout.raw_coarse_mesh_candidates[0]
    p.write_text(
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
        "element face 0\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n"
    )


def _nan_vertices(layout):
    v = np.array([[0, 0, 0], [1, 0, 0], [np.nan, 1, 0]], dtype=float)
    write_mesh(layout.raw_coarse_mesh_candidates[0], make_mesh(v, np.array([[0, 1, 2]])))


def _missing_model(layout):
    for p in layout.raw_sparse_dir.iterdir():
        p.unlink()


def _spherical_camera(layout):
    rec = pycolmap.Reconstruction(str(layout.raw_sparse_dir))
    cam = next(iter(rec.cameras.values()))
    rec.cameras[cam.camera_id].model = pycolmap.CameraModelId.EQUIRECTANGULAR
    rec.write(str(layout.raw_sparse_dir))


def _rename_first(layout, name):
    rec = pycolmap.Reconstruction(str(layout.raw_sparse_dir))
    next(iter(rec.images.values())).name = name
    rec.write(str(layout.raw_sparse_dir))


def _outside_name(layout):
    _rename_first(layout, "../../../../x.png")


def _absolute_name(layout):
    _rename_first(layout, "/tmp/x.png")


def _two_images_one_stem(layout):
    """uav.png and uav.jpg: both would become 01_import/images/uav.png."""
    rec = pycolmap.Reconstruction(str(layout.raw_sparse_dir))
    a, b = list(rec.images.values())[:2]
    stem = a.name.rsplit(".", 1)[0]
    (layout.raw_images_dir / b.name).rename(layout.raw_images_dir / f"{stem}.jpg")
    b.name = f"{stem}.jpg"
    rec.write(str(layout.raw_sparse_dir))


def _nan_pose(layout):
    rec = pycolmap.Reconstruction(str(layout.raw_sparse_dir))
    frame = rec.frames[next(iter(rec.images.values())).frame_id]
    frame.rig_from_world = pycolmap.Rigid3d(frame.rig_from_world.rotation, np.array([np.nan, 0.0, 0.0]))
    rec.write(str(layout.raw_sparse_dir))


@pytest.mark.parametrize(
    "damage, file_part, words",
    [
        (_outside_name, "sparse/0", "'../../../../x.png'"),
        (_absolute_name, "sparse/0", "'/tmp/x.png'"),
        (_two_images_one_stem, "raw/images", ".jpg"),
        (_nan_pose, "sparse/0", "NaN or Inf"),
        (_missing_model, "sparse/0", "missing cameras, images, points3D"),
        (_corrupt, "sparse/0/images.bin", "ends after 11 bytes, inside its first record"),
        (_cut_short("cameras.bin"), "sparse/0/cameras.bin", "inside camera 1 of the 1 it declares"),
        (_cut_short("points3D.bin", keep=0), "sparse/0/points3D.bin", "an empty file"),
        (_cut_short("points3D.bin"), "sparse/0/points3D.bin", "cut short"),
        (_truncated_mesh, "coarse_mesh.ply", "damaged or truncated file (RPly"),
        (_missing_image, "raw/images/", "no file"),
        (_wrong_size, "raw/images/", "12x10"),
        (_no_faces, "coarse_mesh.ply", "no face"),
        (_nan_vertices, "coarse_mesh.ply", "NaN or Inf"),
        (_spherical_camera, "sparse/0/cameras", "EQUIRECTANGULAR"),
    ],
)
def test_bad_input_names_the_file(layout, damage, file_part, words):
    make_raw(layout)
    damage(layout)
    before = tree_digest(layout.raw_dir)
    with pytest.raises(InputError) as e:
        execute(stage, layout, PARAMS)
    msg = str(e.value)
    assert file_part in msg and words in msg and "expected" in msg, msg
    assert "np." not in msg and "std::" not in msg, msg  # words, not a library's reprs
    assert tree_digest(layout.raw_dir) == before
    assert not layout.manifest(stage.NAME).exists()


def test_missing_points_fall_back_to_model_points(layout):
    rec = make_raw(layout, with_points=False)
    manifest = execute(stage, layout, PARAMS)
    assert manifest["metrics"]["points_source"] == "raw/sparse/0 points3D"
    assert manifest["metrics"]["coarse_points"] == rec.num_points3D()


def test_configured_up_axis_is_turned_to_z(layout):
    """A model whose up is -y (COLMAP's habit for upright cameras) comes back z up when configured so."""
    make_raw(layout)
    execute(stage, layout, dataclasses.replace(PARAMS, up_axis="-y"))
    scene = ImportedScene.load(layout)
    assert np.allclose(scene.georef_from_local[:3, :3] @ [0, 0, 1], [0, -1, 0])
    assert "configured" in scene.up_axis_method


def test_up_axis_estimated_from_level_cameras():
    """Level UAV cameras (zero roll, pitched down, many headings) in a frame where -y is up."""
    from facade_pipeline.geometry.camera import look_at
    from facade_pipeline.geometry.frames import estimate_up_from_cameras

    rng = np.random.default_rng(1)
    M = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # model_from_zup: takes +z to -y
    Rs = []
    for az in rng.uniform(0, 2 * np.pi, 12):
        eye = np.array([30 * np.cos(az), 30 * np.sin(az), rng.uniform(10, 40)])
        T = look_at(eye, [0, 0, rng.uniform(0, 20)])
        Rs.append(T[:3, :3] @ M.T)  # cam_from_model
    est = estimate_up_from_cameras(np.array(Rs), snap_deg=15.0)
    assert np.allclose(est.up, [0, -1, 0]) and "snapped" in est.method
    # a single heading (every camera facing the facade) still finds up, from the mean camera up
    T = [look_at([0, -30, h], [0, 0, h - 5]) for h in (5.0, 10.0, 15.0)]
    est = estimate_up_from_cameras(np.array([t[:3, :3] for t in T]), snap_deg=15.0)
    assert np.allclose(est.up, [0, 0, 1])


def test_text_model_and_obj_mesh(layout):
    """COLMAP text models and OBJ meshes, as Metashape and DJI Terra export them, import the same way."""
    import open3d as o3d

    rec = make_raw(layout)
    for p in layout.raw_sparse_dir.iterdir():
        p.unlink()
    rec.write_text(str(layout.raw_sparse_dir))
    ply = layout.raw_coarse_mesh_candidates[0]
    assert o3d.io.write_triangle_mesh(str(layout.raw_coarse_mesh_candidates[1]), read_mesh(ply))
    ply.unlink()
    manifest = execute(stage, layout, PARAMS)
    assert "raw/sparse/0/images.txt" in manifest["inputs"] and "raw/coarse_mesh.obj" in manifest["inputs"]
    assert len(ImportedScene.load(layout).uav_views) == rec.num_reg_images()


def test_two_meshes_is_ambiguous(layout):
    make_raw(layout)
    import shutil

    shutil.copy(layout.raw_coarse_mesh_candidates[0], layout.raw_coarse_mesh_candidates[1])
    with pytest.raises(InputError, match="exactly one coarse mesh"):
        execute(stage, layout, PARAMS)


def test_coarse_mesh_is_cleaned_with_its_geometry_kept(layout):
    """Seams repeat vertices, exports repeat faces, Poisson leaves zero-area faces: all go, colours stay."""
    from facade_pipeline.io.meshes import read_mesh
    from facade_pipeline.meshing.clean import clean_mesh

    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 0, 0], [5, 5, 5], [0, 0, 0], [1, 1, 0]], float)
    f = np.array([[0, 1, 2], [0, 3, 2], [0, 1, 2], [0, 5, 1], [1, 6, 2]])
    colours = np.linspace(0, 1, 21).reshape(7, 3)
    mesh, removed = clean_mesh(make_mesh(v, f, colours))
    assert removed == {"vertices_removed": 3, "faces_removed": 3}
    cv, cf = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    assert sorted(map(tuple, cv[cf].reshape(-1, 3).round(6))) == sorted(
        map(tuple, v[f[[0, 4]]].reshape(-1, 3))
    )  # the two real faces, corner for corner
    assert np.allclose(np.asarray(mesh.vertex_colors)[0], colours[0], atol=1 / 255)  # 8 bits, as in PLY
    make_raw(layout)
    quad = read_mesh(layout.raw_coarse_mesh_candidates[0])
    qv, qf = np.asarray(quad.vertices), np.asarray(quad.triangles)
    write_mesh(layout.raw_coarse_mesh_candidates[0], make_mesh(qv, np.concatenate([qf, qf[:1]])))
    m = execute(stage, layout, PARAMS)["metrics"]
    assert m["coarse_mesh_cleaned"] == {"vertices_removed": 0, "faces_removed": 1}
    assert m["coarse_mesh_triangles"] == len(qf)
