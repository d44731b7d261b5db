"""train_gs and the facade masks of bake_normals: a view without facade pixels is left out of the loss and
counted; no facade pixel in any view stops the run with one line, unless ``mask_by_facade = false``."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from facade_pipeline.errors import InputError
from facade_pipeline.io.images import read_mask, write_mask
from facade_pipeline.manifest import read_manifest
from facade_pipeline.scene import ImportedScene
from stages import train_gs
from stages._runner import execute
from tests.training.conftest import small_params
from tests.training.test_stage import upstream  # noqa: F401  (the fixture)


def _empty_facade_mask(layout, stem: str) -> None:
    path = layout.path("bake_facade_mask", stem=stem)
    write_mask(path, np.zeros_like(read_mask(path)))


def test_no_facade_pixel_in_any_view_stops_with_one_line_unless_masks_are_off(upstream):  # noqa: F811
    views = ImportedScene.load(upstream).uav_views
    for v in views:
        _empty_facade_mask(upstream, v.stem)
    p = small_params(iterations=2)
    assert p.mask_by_facade
    with pytest.raises(InputError) as e:
        execute(train_gs, upstream, p)
    msg = str(e.value)
    assert "masks/facade" in msg and f"none in {len(views)} views" in msg and "mask_by_facade = false" in msg
    assert "\n" not in msg and not upstream.manifest("train_gs").exists()
    # whole images instead: every view trains or is held out, none is left out
    data = train_gs.load_train_data(upstream, dataclasses.replace(p, mask_by_facade=False))
    assert len(data.train_idx) + len(data.test_idx) == len(views) and data.train_idx


def test_a_view_without_facade_pixels_is_left_out_of_the_loss_and_counted(upstream):  # noqa: F811
    views = ImportedScene.load(upstream).uav_views
    p = small_params(iterations=3)
    before = train_gs.load_train_data(upstream, p)
    stem = views[before.train_idx[2]].stem  # a training view
    _empty_facade_mask(upstream, stem)
    data = train_gs.load_train_data(upstream, p)
    assert [views[i].stem for i in data.train_idx] == [
        views[i].stem for i in before.train_idx if views[i].stem != stem
    ]
    execute(train_gs, upstream, p)
    metrics = read_manifest(upstream, "train_gs").metrics
    assert metrics["n_views_without_facade"] == 1
    split = json.loads(upstream.path("train_split").read_text())
    assert stem not in split["train"] and stem not in split["test"]
    assert len(split["train"]) == len(before.train_idx) - 1
