"""gcw_dev's real photos (shared/real/gcw_dev, through regularize_corners: the test run's shared fixture):
registered to the 3D panels, each photo's panel corners reproject closer than with its motion-capture
pose, which scatters them about half a frame bar. Skipped where shared/ is absent."""

from __future__ import annotations

import numpy as np
import pytest

from facade_pipeline.manifest import read_manifest
from facade_pipeline.panels3d.poses import RegisteredPoses, registered_scene
from facade_pipeline.scene import ImportedScene
from tests.conftest import GCW_SRC

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(not (GCW_SRC / "cameras.json").is_file(), reason=f"no real photos at {GCW_SRC}"),
]


def test_registered_poses_reproject_gcw_dev_corners_closer(gcw_dev):
    layout, _ = gcw_dev
    poses = RegisteredPoses.load(layout.path("regularize_poses"))
    summary = read_manifest(layout, "regularize_corners").metrics["poses"]
    assert summary == poses.summary()
    refined = [v for v in poses.views if v.refined]
    assert len(refined) >= 8 and len(poses.views) == 11  # of the eleven photos
    for v in refined:
        assert v.reprojection_px < v.reprojection_imported_px
    for v in poses.views:
        if not v.refined:
            assert v.reason and np.isclose(v.reprojection_px, v.reprojection_imported_px, equal_nan=True)
    # about 10 px with the motion-capture poses; the corners' own scatter (segmentation) is 2-3 px
    assert summary["reprojection_median_px"] < 0.5 * summary["reprojection_median_px_imported"]
    # every photo is a frontal view and a UAV view: the UAV view takes the frontal view's registered pose
    imported = {(v.role, v.stem): v.camera for v in ImportedScene.load(layout).views}
    for v in registered_scene(layout).views:
        T = {p.stem: p for p in poses.views}[v.stem]
        assert np.array_equal(v.camera.cam_from_world, T.cam_from_world)
        assert np.array_equal(v.camera.K, imported[(v.role, v.stem)].K)
