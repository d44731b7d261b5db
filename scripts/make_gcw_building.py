"""Make a building's raw/ from posed photos of a glass curtain wall (the layout of ``shared/real/gcw_dev``).

    python scripts/make_gcw_building.py SRC_DIR --building NAME [--data-root DIR] [--scale S]

SRC_DIR holds ``images/*.jpg`` and ``cameras.json`` (``{img: {K, cam_from_world, width, height}}``: K in
OpenCV's pixel convention, ``cam_from_world`` from the wall frame to OpenCV camera axes, metres). Its
``masks/`` and ``panes.json`` are the truth and are not read. Writes ``<data_root>/<NAME>/raw/`` as a user's
photogrammetry would give it:

- the photos both as frontal views (``raw/frontal/``) and as UAV views (``raw/images``), each with a
  PINHOLE COLMAP model from the poses;
- the world frame z up: the wall frame's y points down (gravity), so world = (x, z, -y) of the wall frame;
- ``coarse_mesh.ply``: the wall-plane rectangle covering every photo's footprint (with a margin), a grid of
  cells with Gaussian noise along the wall normal (``--noise-mm``), and ``coarse_points.ply`` sampled on it,
  each point coloured by the median of the photos that see it;
- the sparse point cloud photogrammetry triangulates from the photos (``triangulate``): COLMAP's SIFT
  features (pycolmap), matched between every pair of photos, kept where they agree with the known poses'
  epipolar geometry (``--epipolar-px``) and triangulated against the fixed poses. It is added to
  ``coarse_points.ply`` and is the UAV model's points3D. Most of its points are features of the
  reflections: a plane mirror's image is a consistent 3D point as far behind the glass as the mirrored
  object stands in front of it, so they lie behind the wall (virtual points); the rest lie on the frames.
  The pipeline keeps them as a user's photogrammetry gives them; the reflection model's proxy mirrors the
  virtual points back in front of the glass (``shading.surroundings.unmirror``).

``--scale S`` makes the same photos of a wall S times the size (the poses' positions and the coarse mesh's
noise times S, as a full-size wall seen from S times as far with the same cameras would give them).

Refuses to write into an existing raw/ unless ``--force``; nothing is written outside the data root.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from facade_pipeline.errors import InputError, PipelineError  # noqa: E402
from facade_pipeline.geometry.camera import PinholeCamera  # noqa: E402
from facade_pipeline.io.colmap import ColmapView, write_pinhole_model  # noqa: E402
from facade_pipeline.io.meshes import make_mesh, make_points, write_mesh, write_points  # noqa: E402
from facade_pipeline.layout import BuildingLayout, resolve_data_root  # noqa: E402

# world (z up) from the wall frame (x along rows, y down, z into the wall): x -> x, z -> y, -y -> z
WORLD_FROM_WALL = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, -1.0, 0.0, 0.0],
                            [0.0, 0.0, 0.0, 1.0]])


def read_cameras(src: Path, scale: float = 1.0) -> dict[str, PinholeCamera]:
    """The photos' cameras in the world frame (pixel centres at +0.5, as everywhere in the pipeline), of a
    wall ``scale`` times the size (the cameras' positions scaled about the wall frame's origin)."""
    path = src / "cameras.json"
    try:
        raw = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise InputError(path, "a JSON object {img: {K, cam_from_world, width, height}}",
                         f"{type(e).__name__}: {e}") from None
    cams = {}
    for stem, c in sorted(raw.items()):
        try:
            K = np.array(c["K"], float)
            T = np.array(c["cam_from_world"], float)
            w, h = int(c["width"]), int(c["height"])
        except (KeyError, TypeError, ValueError) as e:
            raise InputError(path, f"K, cam_from_world, width, height for {stem!r}", repr(e)) from None
        if K.shape != (3, 3) or T.shape != (4, 4) or not (np.isfinite(K).all() and np.isfinite(T).all()):
            raise InputError(path, f"a finite 3 x 3 K and 4 x 4 cam_from_world for {stem!r}",
                             f"shapes {K.shape} and {T.shape}")
        K, T = K.copy(), T.copy()
        T[:3, 3] *= scale  # a camera at s C: t = -R C scales with it
        K[:2, 2] += 0.5  # OpenCV's top-left pixel centre (0, 0) -> (0.5, 0.5)
        cams[stem] = PinholeCamera(K, T @ np.linalg.inv(WORLD_FROM_WALL), w, h)
    return cams


def footprint_wall(cams: dict[str, PinholeCamera], samples: int = 9) -> np.ndarray:
    """[N, 2] wall-frame (x, y) points where the rays of each photo's border meet the wall plane z = 0."""
    wall_from_world = np.linalg.inv(WORLD_FROM_WALL)
    out = []
    for cam in cams.values():
        t = np.linspace(0.0, 1.0, samples)
        W, H = cam.width, cam.height
        xs = np.concatenate([t * W, np.full_like(t, W), t * W, np.zeros_like(t)])
        ys = np.concatenate([np.zeros_like(t), t * H, np.full_like(t, H), t * H])
        o, d = cam.pixel_rays(xs, ys)
        o = o @ wall_from_world[:3, :3].T + wall_from_world[:3, 3]
        d = d @ wall_from_world[:3, :3].T
        lam = -o[:, 2] / d[:, 2]
        ok = lam > 0
        out.append((o[ok] + lam[ok, None] * d[ok])[:, :2])
    return np.concatenate(out)


def coarse_wall(xy: np.ndarray, noise_m: float, cell_m: float, margin: float,
                rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Vertices [V, 3] (world) and triangles [T, 3] of the noisy wall rectangle covering the footprint
    points ``xy`` [N, 2] (wall frame), ``margin`` of its size beyond them on every side."""
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    pad = margin * (hi - lo)
    lo, hi = lo - pad, hi + pad
    nx, ny = (np.ceil((hi - lo) / cell_m).astype(int) + 1).tolist()
    gx, gy = np.meshgrid(np.linspace(lo[0], hi[0], nx), np.linspace(lo[1], hi[1], ny))
    wall = np.stack([gx.ravel(), gy.ravel(), rng.normal(0.0, noise_m, gx.size)], axis=1)
    idx = np.arange(nx * ny).reshape(ny, nx)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    tris = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    world = wall @ WORLD_FROM_WALL[:3, :3].T
    return world, tris


def point_colours(points: np.ndarray, cams: dict[str, PinholeCamera], images: list[Path]) -> np.ndarray:
    """[N, 3] colour in [0, 1] of each world point: the median over the photos it projects into (grey where
    none), as a photogrammetric point cloud colours its points."""
    from facade_pipeline.io.images import read_image

    seen = []
    for path in images:
        cam = cams[path.stem]
        uv, z = cam.project(points)
        with np.errstate(invalid="ignore"):
            x, y = np.floor(uv[:, 0]), np.floor(uv[:, 1])
            ok = (z > 0) & (x >= 0) & (y >= 0) & (x < cam.width) & (y < cam.height)
        col = np.full((len(points), 3), np.nan)
        img = read_image(path)
        col[ok] = img[y[ok].astype(int), x[ok].astype(int)] / 255.0
        seen.append(col)
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # points no photo sees: an all-NaN median
        med = np.nanmedian(np.stack(seen), axis=0)
    return np.where(np.isfinite(med), med, 0.5)


def _skew(t: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])


def epipolar_inliers(cam_a: PinholeCamera, cam_b: PinholeCamera, xa: np.ndarray, xb: np.ndarray,
                     tol_px: float) -> np.ndarray:
    """[M] bool: the matches ``xa`` <-> ``xb`` ([M, 2] pixels of a and b) whose Sampson distance to the
    epipolar geometry of the two cameras' poses is within ``tol_px``."""
    T = cam_b.cam_from_world @ np.linalg.inv(cam_a.cam_from_world)
    F = np.linalg.inv(cam_b.K).T @ _skew(T[:3, 3]) @ T[:3, :3] @ np.linalg.inv(cam_a.K)
    ha, hb = np.c_[xa, np.ones(len(xa))], np.c_[xb, np.ones(len(xb))]
    fa, fb = ha @ F.T, hb @ F
    num = np.einsum("ij,ij->i", hb, fa) ** 2
    den = fa[:, 0] ** 2 + fa[:, 1] ** 2 + fb[:, 0] ** 2 + fb[:, 1] ** 2
    return num <= tol_px**2 * den


def triangulate(image_dir: Path, cams: dict[str, PinholeCamera], names: list[str], work: Path,
                tol_px: float) -> tuple[np.ndarray, np.ndarray]:
    """The sparse point cloud of the photos ``names`` in ``image_dir`` (module docstring), triangulated
    against the fixed poses ``cams`` with COLMAP's tools in the empty folder ``work``: xyz [N, 3] (world,
    m) and colours [N, 3] in [0, 1], sorted by position (the same photos give the same file)."""
    import pycolmap

    level = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 2  # COLMAP's per-image INFO lines; the script prints its own
    try:
        db_path = work / "database.db"
        pycolmap.Database.open(str(db_path)).close()
        K = cams[Path(names[0]).stem].K
        if any(not np.allclose(cams[Path(n).stem].K, K) for n in names):
            raise InputError(image_dir.parent / "cameras.json", "one K for every photo (one camera)",
                             "several; give each camera its own folder")
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = "PINHOLE"
        reader.camera_params = ",".join(f"{v:.12g}" for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
        single = pycolmap.CameraMode.SINGLE
        # imported one by one before the threaded extraction, so that the ids follow the names' order
        pycolmap.import_images(db_path, image_dir, camera_mode=single, image_names=names, options=reader)
        print(f"triangulate: SIFT features of {len(names)} photos", file=sys.stderr, flush=True)
        pycolmap.extract_features(db_path, image_dir, image_names=names, camera_mode=single,
                                  reader_options=reader, device=pycolmap.Device.cpu)
        print("triangulate: matching every pair", file=sys.stderr, flush=True)
        pycolmap.match_exhaustive(db_path, device=pycolmap.Device.cpu)
        db = pycolmap.Database.open(str(db_path))
        try:
            images = sorted(db.read_all_images(), key=lambda im: im.image_id)
            rec = pycolmap.Reconstruction()
            for camera in db.read_all_cameras():
                rec.add_camera_with_trivial_rig(camera)
            for im in images:
                T = cams[Path(im.name).stem].cam_from_world
                rec.add_image_with_trivial_frame(
                    pycolmap.Image(name=im.name, camera_id=im.camera_id, image_id=im.image_id),
                    pycolmap.Rigid3d(pycolmap.Rotation3d(T[:3, :3]), T[:3, 3].copy()))
            # the verified matches are those the known poses allow, not the model COLMAP's RANSAC picks
            # (a homography of the wall's plane, which drops every reflection)
            for a, im_a in enumerate(images):
                for im_b in images[a + 1:]:
                    ia, ib = im_a.image_id, im_b.image_id
                    db.delete_two_view_geometry(ia, ib)
                    m = db.read_matches(ia, ib)
                    if len(m) == 0:
                        continue
                    ca, cb = cams[Path(im_a.name).stem], cams[Path(im_b.name).stem]
                    ok = epipolar_inliers(ca, cb, db.read_keypoints(ia)[m[:, 0], :2],
                                          db.read_keypoints(ib)[m[:, 1], :2], tol_px)
                    geometry = pycolmap.TwoViewGeometry()
                    geometry.config = pycolmap.TwoViewGeometryConfiguration.CALIBRATED
                    geometry.inlier_matches = np.ascontiguousarray(m[ok])
                    db.write_two_view_geometry(ia, ib, geometry)
        finally:
            db.close()
        print("triangulate: points from the fixed poses", file=sys.stderr, flush=True)
        options = pycolmap.IncrementalPipelineOptions()
        tri = options.triangulation
        tri.merge_max_reproj_error = tri.complete_max_reproj_error = tol_px
        options.mapper.filter_max_reproj_error = tol_px
        tri.random_seed = options.mapper.random_seed = 0
        (work / "model").mkdir()
        out = pycolmap.triangulate_points(rec, db_path, image_dir, work / "model", options=options)
    finally:
        pycolmap.logging.minloglevel = level
    pts = list(out.points3D.values())
    xyz = np.array([p.xyz for p in pts], np.float64).reshape(-1, 3)
    rgb = np.array([p.color for p in pts], np.float64).reshape(-1, 3) / 255.0
    order = np.lexsort(xyz.T[::-1])
    return xyz[order], rgb[order]


def make_building(src: Path, layout: BuildingLayout, noise_m: float, n_points: int, seed: int,
                  force: bool, scale: float = 1.0, epipolar_px: float = 8.0) -> dict:
    """Write raw/ (module docstring) of the wall at ``scale`` (``noise_m`` is the noise at that scale);
    returns counts for the summary line."""
    images = sorted((src / "images").glob("*.jpg")) + sorted((src / "images").glob("*.png"))
    if not images:
        raise InputError(src / "images", "photos (*.jpg or *.png)", "none")
    cams = read_cameras(src, scale)
    missing = sorted({p.stem for p in images} - set(cams))
    if missing:
        raise InputError(src / "cameras.json", "a camera for every photo", f"none for {', '.join(missing)}")
    if layout.raw_dir.exists() and any(layout.raw_dir.iterdir()):
        if not force:
            raise InputError(layout.raw_dir, "no raw/ yet (or --force to replace it)", "an existing raw/")
        shutil.rmtree(layout.raw_dir)
    rng = np.random.default_rng(seed)
    views = [ColmapView(p.name, cams[p.stem]) for p in images]
    layout.raw_dir.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix=".triangulate-", dir=layout.raw_dir) as work:
        sparse_xyz, sparse_rgb = triangulate(src / "images", cams, [p.name for p in images], Path(work),
                                             epipolar_px)
    for img_dir, model_dir, xyz in ((layout.raw_images_dir, layout.raw_sparse_dir, sparse_xyz),
                                    (layout.raw_frontal_images_dir, layout.raw_frontal_sparse_dir, None)):
        img_dir.mkdir(parents=True, exist_ok=True)
        for p in images:
            shutil.copyfile(p, img_dir / p.name)
        rgb = None if xyz is None else np.round(255.0 * sparse_rgb).astype(np.uint8)
        write_pinhole_model(model_dir, views, xyz, rgb)
    # cells of a tenth of the smaller footprint side: a photogrammetric mesh of a wall is coarse and bumpy
    xy = footprint_wall(cams)
    cell = 0.1 * float(np.min(xy.max(axis=0) - xy.min(axis=0)))
    verts, tris = coarse_wall(xy, noise_m, cell, 0.1, rng)
    mesh = make_mesh(verts, tris)
    write_mesh(layout.raw_coarse_mesh_candidates[0], mesh)
    # points on random triangles (the cells are equal, so uniform by area), with their own noise
    t = tris[rng.integers(0, len(tris), n_points)]
    ab = rng.random((n_points, 2))
    flip = ab.sum(axis=1) > 1.0
    ab[flip] = 1.0 - ab[flip]
    a, b, c = verts[t[:, 0]], verts[t[:, 1]], verts[t[:, 2]]
    pts = a + ab[:, :1] * (b - a) + ab[:, 1:] * (c - a)
    pts = pts + rng.normal(0.0, noise_m, (n_points, 1)) * WORLD_FROM_WALL[:3, 2]
    cols = point_colours(pts, cams, images)
    write_points(layout.raw_coarse_points,
                 make_points(np.concatenate([pts, sparse_xyz]), np.concatenate([cols, sparse_rgb])))
    return {"photos": len(images), "mesh_triangles": len(tris), "points": len(pts),
            "triangulated": len(sparse_xyz)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("src", type=Path, help="folder with images/ and cameras.json")
    ap.add_argument("--building", required=True, help="name of the building to make")
    ap.add_argument("--data-root", default=None, help="data root (default: data/ or $FACADE_DATA_ROOT)")
    ap.add_argument("--noise-mm", type=float, default=2.0, help="coarse mesh noise along the normal (mm)")
    ap.add_argument("--points", type=int, default=20000, help="coarse points sampled on the mesh")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--force", action="store_true", help="replace an existing raw/")
    ap.add_argument("--epipolar-px", type=float, default=8.0,
                    help="a match is kept within this distance of the poses' epipolar lines (px): the poses' "
                         "error (motion capture's 5 mm at 0.3 m is 15 px) and the features' (1-2 px)")
    ap.add_argument("--scale", type=float, default=1.0,
                    help="the wall this many times the size: poses and mesh noise scaled (-)")
    a = ap.parse_args(argv)
    if not (np.isfinite(a.scale) and a.scale > 0):
        print(f"error: --scale: expected a positive number, found {a.scale}; give the wall's size factor",
              file=sys.stderr)
        return 2
    try:
        layout = BuildingLayout(resolve_data_root(a.data_root), a.building)
        stats = make_building(a.src, layout, a.noise_mm * 1e-3 * a.scale, a.points, a.seed, a.force, a.scale,
                              a.epipolar_px)
    except PipelineError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"{layout.raw_dir}: {stats['photos']} photos (frontal and UAV), coarse mesh of "
          f"{stats['mesh_triangles']} triangles, {stats['points']} coarse points on it and "
          f"{stats['triangulated']} triangulated from the photos")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
