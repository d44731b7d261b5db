"""Lines that must let a person find the culprit in a model of hundreds of images: a pose with NaN or Inf
names the image and the model, two images that would share an output name are both named."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest

from facade_pipeline.config import default_params
from facade_pipeline.errors import InputError
from stages import import_photogrammetry as imp
from tests.helpers import make_raw

PARAMS = default_params("import_photogrammetry", imp.Params)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_a_non_finite_pose_names_the_image_and_the_model(layout, bad):
    make_raw(layout)
    rec = pycolmap.Reconstruction(str(layout.raw_sparse_dir))
    image = list(rec.images.values())[2]
    frame = rec.frames[image.frame_id]
    frame.rig_from_world = pycolmap.Rigid3d(frame.rig_from_world.rotation, np.array([0.0, bad, 0.0]))
    rec.write(str(layout.raw_sparse_dir))
    with pytest.raises(InputError) as e:
        imp.inputs(layout, PARAMS)
    msg = str(e.value)
    assert msg.startswith(str(layout.raw_sparse_dir) + ":"), msg
    assert f"image {image.name}" in msg and "NaN or Inf" in msg
    others = [im.name for im in rec.images.values() if im.name != image.name]
    assert not any(name in msg for name in others)


def test_two_images_with_one_stem_are_both_named(layout):
    make_raw(layout)
    rec = pycolmap.Reconstruction(str(layout.raw_sparse_dir))
    a, b = list(rec.images.values())[1:3]
    stem = a.name.rsplit(".", 1)[0]
    (layout.raw_images_dir / b.name).rename(layout.raw_images_dir / f"{stem}.jpg")
    b.name = f"{stem}.jpg"
    rec.write(str(layout.raw_sparse_dir))
    with pytest.raises(InputError) as e:
        imp.inputs(layout, PARAMS)
    msg = str(e.value)
    assert a.name in msg and f"{stem}.jpg" in msg and a.name != f"{stem}.jpg"
    assert str(layout.raw_images_dir) in msg and str(layout.raw_sparse_dir) in msg
    assert "rename one" in msg and "\n" not in msg
