"""The one path registry. Every file the pipeline reads or writes is built here from a pattern in
``ENTRIES``; ``data_layout.md`` describes the same patterns and a test keeps the two in sync.

Paths are per building: ``<data_root>/<building>/...``. The data root is ``data/`` under the current
directory unless the ``FACADE_DATA_ROOT`` environment variable or an explicit argument (doit's
``data_root=`` variable, a stage's ``--data-root``) moves it.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

DATA_ROOT_ENV = "FACADE_DATA_ROOT"
DEFAULT_DATA_ROOT = "data"

#: Pipeline stages in order, with their output folder. ``synthesize`` writes raw/ and gt/ instead.
STAGE_DIRS: dict[str, str] = {
    "import_photogrammetry": "01_import",
    "rectify": "02_rectify",
    "segment_panels": "03_segment",
    "regularize_corners": "04_regularize",
    "correct_mesh": "05_correct_mesh",
    "bake_normals": "06_bake_normals",
    "train_gs": "07_train",
    "evaluate": "08_evaluate",
}

#: key -> pattern relative to the building folder. ``{name}`` fields are filled per call.
ENTRIES: dict[str, str] = {
    # what the user brings
    "raw_dir": "raw",
    "raw_images_dir": "raw/images",
    "raw_image": "raw/images/{name}",
    "raw_sparse_dir": "raw/sparse/0",
    "raw_frontal_images_dir": "raw/frontal/images",
    "raw_frontal_image": "raw/frontal/images/{name}",
    "raw_frontal_sparse_dir": "raw/frontal/sparse/0",
    "raw_coarse_mesh_ply": "raw/coarse_mesh.ply",
    "raw_coarse_mesh_obj": "raw/coarse_mesh.obj",
    "raw_coarse_points": "raw/coarse_points.ply",
    # ground truth of synthetic buildings (never read by the stages it evaluates)
    "gt_dir": "gt",
    "gt_manifest": "gt/manifest.json",
    "gt_previous_outputs": "gt/.previous_outputs.json",
    "gt_scene": "gt/scene.json",
    "gt_facade_mesh": "gt/facade_mesh.ply",
    "gt_glass_mesh": "gt/glass_mesh.ply",
    "gt_frame_mesh": "gt/frame_mesh.ply",
    "gt_body_mesh": "gt/body_mesh.ply",
    "gt_panels": "gt/panels.json",
    "gt_sparse_dir": "gt/sparse/0",
    "gt_frontal_sparse_dir": "gt/frontal/sparse/0",
    "gt_clean_image": "gt/clean/{stem}.png",
    "gt_normal_map": "gt/normals/{stem}.exr",
    "gt_depth_map": "gt/depth/{stem}.exr",
    "gt_reflectivity_map": "gt/reflectivity/{stem}.exr",
    "gt_glass_mask": "gt/masks/glass/{stem}.png",
    "gt_frame_mask": "gt/masks/frame/{stem}.png",
    "gt_facade_mask": "gt/masks/facade/{stem}.png",
    # 01_import: the normalised, undistorted scene
    "import_scene": "01_import/scene.json",
    "import_image": "01_import/images/{stem}.png",
    "import_frontal_image": "01_import/frontal/{stem}.png",
    "import_sparse_dir": "01_import/sparse/0",
    "import_frontal_sparse_dir": "01_import/frontal_sparse/0",
    "import_coarse_mesh": "01_import/coarse_mesh.ply",
    "import_coarse_points": "01_import/coarse_points.ply",
    # 02_rectify: curved facades unfolded into planar-facade images, per frontal view
    "rectify_image": "02_rectify/images/{stem}.png",
    "rectify_mapping": "02_rectify/mappings/{stem}.json",
    "rectify_surface": "02_rectify/surfaces/{stem}.json",
    "rectify_overlay": "02_rectify/overlays/{stem}.png",
    # 03_segment: panels found in each frontal view (formats in data_layout.md, "Hand-off formats")
    "segment_corners": "03_segment/corners/{stem}.json",
    "segment_mask": "03_segment/masks/{stem}.png",
    "segment_overlay": "03_segment/overlays/{stem}.png",
    # 04-06: 3D panels, corrected mesh, baked geometry prior of the training views
    "regularize_panels": "04_regularize/panels.json",
    "regularize_poses": "04_regularize/poses.json",
    "regularize_overlay": "04_regularize/overlays/{stem}.png",
    "correct_mesh": "05_correct_mesh/corrected_mesh.ply",
    "correct_mesh_labels": "05_correct_mesh/triangle_labels.npy",
    "correct_mesh_overlay": "05_correct_mesh/overlay.png",
    "bake_normal_map": "06_bake_normals/normals/{stem}.exr",
    "bake_depth_map": "06_bake_normals/depth/{stem}.exr",
    "bake_facade_mask": "06_bake_normals/masks/facade/{stem}.png",
    "bake_glass_mask": "06_bake_normals/masks/glass/{stem}.png",
    # 07_train: the trained Gaussians and what produced them
    "train_ply": "07_train/gaussians.ply",
    "train_reflection": "07_train/reflection.pt",
    "train_split": "07_train/split.json",
    "train_log": "07_train/train_log.jsonl",
    "train_checkpoint": "07_train/checkpoint.pt",
    # more trained variants (a baseline, an ablation), saved beside 07_train for evaluate to compare
    "variant_dir": "variants/{variant}",
    # 08_evaluate: metrics, renders beside ground truth, the report
    "eval_metrics": "08_evaluate/metrics.json",
    "eval_render": "08_evaluate/renders/{variant}/{split}/{stem}.png",
    "eval_comparison": "08_evaluate/comparisons/{variant}/{split}/{stem}.png",
    "eval_report_md": "08_evaluate/report.md",
    "eval_report_html": "08_evaluate/report.html",
    "eval_video": "08_evaluate/flythrough.mp4",
    "eval_clip": "08_evaluate/flythrough.webp",
    # every stage folder ends with its manifest
    "stage_dir": "{stage_dir}",
    "stage_manifest": "{stage_dir}/manifest.json",
    # while a stage reruns: the outputs its last completed run listed, until this run replaces them
    "stage_previous_outputs": "{stage_dir}/.previous_outputs.json",
    # doit's state, kept per building
    "doit_db": ".doit.db",
    # held by the run that works on the building (one at a time)
    "lock": ".lock",
    # facade-batch's record of the building's stages, and each stage's output on the worker that ran it
    "batch_record": ".batch/status.json",
    "batch_log": ".batch/{stage}.log",
}


def resolve_data_root(explicit: str | Path | None = None) -> Path:
    """The data root: ``explicit`` if given, else ``$FACADE_DATA_ROOT``, else ``./data``."""
    if explicit:
        return Path(explicit).expanduser().resolve()
    env = os.environ.get(DATA_ROOT_ENV)
    return Path(env).expanduser().resolve() if env else (Path.cwd() / DEFAULT_DATA_ROOT).resolve()


def entry_regex(key: str) -> re.Pattern[str]:
    """The paths (relative to the building) of entry ``key`` with any fields, and of files under it."""
    parts = re.split(r"\{\w+\}", ENTRIES[key])
    return re.compile(".+".join(re.escape(p) for p in parts) + r"(/.+)?\Z")


_NAME_RE = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]*$")


@dataclass(frozen=True)
class BuildingLayout:
    """Paths of one building's data. Pure: building a path never touches the disk."""

    data_root: Path
    building: str

    def __post_init__(self) -> None:
        if not _NAME_RE.match(self.building):
            raise ValueError(f"building name {self.building!r} must be letters, digits, '_', '.', '-'")
        object.__setattr__(self, "data_root", Path(self.data_root))

    @classmethod
    def for_building(cls, building: str, data_root: str | Path | None = None) -> BuildingLayout:
        return cls(resolve_data_root(data_root), building)

    @property
    def root(self) -> Path:
        return self.data_root / self.building

    def path(self, key: str, **fields: str) -> Path:
        """The path of entry ``key`` with its ``{fields}`` filled in."""
        return self.root / ENTRIES[key].format(**fields)

    def relative(self, path: str | Path) -> str:
        """``path`` relative to the building folder, with forward slashes (as manifests record it).

        Lexical: a folder of the building that is a symlink (photos or a stage's outputs on another disk)
        keeps its place in the building, so its files are named as if it were a plain folder."""
        rel = Path(os.path.normpath(os.path.abspath(path))).relative_to(self.root)
        return rel.as_posix()

    # --- raw ---
    @property
    def raw_dir(self) -> Path:
        return self.path("raw_dir")

    @property
    def raw_images_dir(self) -> Path:
        return self.path("raw_images_dir")

    def raw_image(self, name: str) -> Path:
        return self.path("raw_image", name=name)

    @property
    def raw_sparse_dir(self) -> Path:
        return self.path("raw_sparse_dir")

    @property
    def raw_frontal_images_dir(self) -> Path:
        return self.path("raw_frontal_images_dir")

    def raw_frontal_image(self, name: str) -> Path:
        return self.path("raw_frontal_image", name=name)

    @property
    def raw_frontal_sparse_dir(self) -> Path:
        return self.path("raw_frontal_sparse_dir")

    @property
    def raw_coarse_mesh_candidates(self) -> tuple[Path, Path]:
        """The coarse mesh may come as PLY or OBJ; exactly one of these must exist."""
        return self.path("raw_coarse_mesh_ply"), self.path("raw_coarse_mesh_obj")

    @property
    def raw_coarse_points(self) -> Path:
        return self.path("raw_coarse_points")

    # --- gt ---
    @property
    def gt_dir(self) -> Path:
        return self.path("gt_dir")

    def gt(self, key: str, stem: str | None = None) -> Path:
        """A ground-truth artefact: ``gt(\"glass_mesh\")`` or ``gt(\"normal_map\", stem)``."""
        return self.path("gt_" + key, **({} if stem is None else {"stem": stem}))

    # --- stages ---
    def stage_dir(self, stage: str) -> Path:
        return self.path("stage_dir", stage_dir=STAGE_DIRS[stage])

    def manifest(self, stage: str) -> Path:
        """The manifest of ``stage``; ``synthesize`` keeps its manifest in gt/."""
        if stage == "synthesize":
            return self.path("gt_manifest")
        return self.path("stage_manifest", stage_dir=STAGE_DIRS[stage])

    def previous_outputs(self, stage: str) -> Path:
        """Where a rerun of ``stage`` keeps the output list of its last completed run (whose manifest it
        deleted) until it has replaced them, so that a run interrupted in between still knows them."""
        if stage == "synthesize":
            return self.path("gt_previous_outputs")
        return self.path("stage_previous_outputs", stage_dir=STAGE_DIRS[stage])

    # --- 01_import ---
    @property
    def import_scene(self) -> Path:
        return self.path("import_scene")

    def import_image(self, stem: str) -> Path:
        return self.path("import_image", stem=stem)

    def import_frontal_image(self, stem: str) -> Path:
        return self.path("import_frontal_image", stem=stem)

    @property
    def import_sparse_dir(self) -> Path:
        return self.path("import_sparse_dir")

    @property
    def import_frontal_sparse_dir(self) -> Path:
        return self.path("import_frontal_sparse_dir")

    @property
    def import_coarse_mesh(self) -> Path:
        return self.path("import_coarse_mesh")

    @property
    def import_coarse_points(self) -> Path:
        return self.path("import_coarse_points")

    @property
    def doit_db(self) -> Path:
        return self.path("doit_db")

    @property
    def lock(self) -> Path:
        return self.path("lock")
