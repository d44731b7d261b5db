"""scripts/make_gcw_building.py's wall at another size (``--scale``): the cameras' centres scale about the
wall frame's origin, their orientation and intrinsics stay; a size factor that is no positive number is one
line and exit code 2."""

from __future__ import annotations

import numpy as np
import pytest

from scripts.make_gcw_building import main, read_cameras
from tests.segmentation.conftest import REPO

SRC = REPO.parent / "shared" / "real" / "gcw_dev"
pytestmark = pytest.mark.skipif(not (SRC / "cameras.json").is_file(), reason=f"no real photos at {SRC}")


def test_scale_moves_the_cameras_about_the_wall():
    one, big = read_cameras(SRC), read_cameras(SRC, 25.0)
    assert one.keys() == big.keys()
    for stem, cam in one.items():
        np.testing.assert_allclose(big[stem].center, 25.0 * cam.center, rtol=1e-12, atol=1e-12)
        np.testing.assert_array_equal(big[stem].K, cam.K)
        np.testing.assert_array_equal(big[stem].cam_from_world[:3, :3], cam.cam_from_world[:3, :3])


@pytest.mark.parametrize("value", ["0", "-2", "nan"])
def test_a_scale_that_is_no_size_is_one_line(value, tmp_path, capsys):
    assert main([str(SRC), "--building", "b", "--data-root", str(tmp_path), "--scale", value]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--scale" in err and value in err
    assert not (tmp_path / "b").exists()
