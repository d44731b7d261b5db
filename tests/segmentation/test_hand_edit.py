"""A panel mask fixed by hand (03_segment/masks/<stem>.png) is picked up downstream and never reruns
rectify or segment_panels (the mask is their output, not their input)."""

from __future__ import annotations

import re

from facade_pipeline.io.images import read_mask, write_mask
from tests.segmentation.conftest import doit


def executed(stdout: str) -> list[str]:
    return re.findall(r"^\.  (\S+)", stdout, flags=re.M)


def test_mask_edit_reruns_nothing_upstream(scenes):
    layout, env = scenes["synthetic64"]
    mask_path = layout.path("segment_mask", stem="frontal_0000")
    before = mask_path.read_bytes()
    try:
        mask = read_mask(mask_path)
        mask[:6, :6] = ~mask[:6, :6]  # a person paints a corner
        write_mask(mask_path, mask)
        # (the stages after segment_panels are left out here: they are checked by their own tests)
        ran = executed(doit(["segment_panels", "building=synthetic64"], env, layout.data_root))
        assert "rectify" not in ran and "segment_panels" not in ran
        assert read_mask(mask_path)[:6, :6].tolist() == mask[:6, :6].tolist()  # the edit survives
    finally:
        mask_path.write_bytes(before)
