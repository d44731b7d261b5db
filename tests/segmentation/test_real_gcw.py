"""Real photos of a glass curtain wall with truth (shared/real/gcw_dev): scripts/make_gcw_building.py makes
the building, the DAG runs through regularize_corners with configs/buildings/gcw_dev.toml (one setting for
every photo), and the result is measured against the truth masks, the pane outlines and the nominal grid.
The thresholds guard what the method reaches today; the stricter targets and the figures against them are
in benchmarks/RESULTS.md (bench_segmentation.py --real). Skipped where shared/ is absent."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from facade_pipeline.layout import BuildingLayout
from facade_pipeline.manifest import read_manifest
from facade_pipeline.segmentation.real_truth import (
    EXPOSURES,
    evaluate_building,
    exposed_copy,
    grid_corner_errors_m,
    iou,
    summary,
)
from facade_pipeline.segmentation.result import ViewSegmentation
from facade_pipeline.threads import usable_cores
from scripts.make_gcw_building import WORLD_FROM_WALL
from tests.conftest import GCW_SRC
from tests.segmentation.conftest import REPO, _cmd, doit

SRC = GCW_SRC
pytestmark = [pytest.mark.slow,
              pytest.mark.skipif(not (SRC / "cameras.json").is_file(), reason=f"no real photos at {SRC}")]


@pytest.fixture(scope="module")
def gcw(gcw_dev):
    """The test run's gcw_dev (tests/conftest.py, through regularize_corners) and its figures per photo."""
    layout, _ = gcw_dev
    return layout, evaluate_building(layout, SRC)


def test_script_writes_raw_as_a_user_would_bring_it(gcw, tmp_path):
    layout, _ = gcw
    n = len(list((SRC / "images").glob("*.jpg")))
    assert len(list(layout.raw_images_dir.iterdir())) == n
    assert len(list(layout.raw_frontal_images_dir.iterdir())) == n
    assert layout.raw_coarse_mesh_candidates[0].is_file() and layout.raw_coarse_points.is_file()
    again = subprocess.run([sys.executable, str(REPO / "scripts" / "make_gcw_building.py"), str(SRC),
                            "--building", "gcw_dev", "--data-root", str(layout.data_root)], cwd=REPO,
                           capture_output=True, text=True)
    assert again.returncode == 2 and "existing raw/" in again.stderr and "Traceback" not in again.stderr


def test_every_photo_is_rectified_by_a_plane_at_its_own_scale(gcw):
    layout, _ = gcw
    m = read_manifest(layout, "rectify").metrics
    assert m["n_plane"] == m["n_views"] == len(list((SRC / "images").glob("*.jpg")))
    cams = json.loads((SRC / "cameras.json").read_text())
    for stem, v in m["views"].items():
        c = cams[stem]
        depth = float(np.asarray(c["cam_from_world"])[2, 3])  # the wall's distance along the optical axis
        gsd = abs(depth) / c["K"][0][0]
        assert 0.7 < v["metres_per_px"] / gsd < 1.5  # oblique views spread the footprint about it


def test_segmentation_against_the_truth(gcw):
    _, per_photo = gcw
    s = summary(per_photo)
    assert s["photos"] == 11
    assert s["found_fraction"] >= 0.9
    assert s["mask_iou_median"] >= 0.75 and s["mask_iou_min"] >= 0.45
    assert s["corner_error_median_px"] <= 3.0
    assert s["complete_less_than_half_glass"] <= 3


def test_3d_panels_against_the_nominal_grid(gcw):
    layout, _ = gcw
    panels = json.loads(layout.path("regularize_panels").read_text())["panels"]
    assert len(panels) >= 4
    world = np.array([p["corners"] for p in panels], float).reshape(-1, 3)
    wall = world @ WORLD_FROM_WALL[:3, :3]  # world -> wall frame (a rotation)
    err = grid_corner_errors_m(wall, (0.1032, 0.1532), (0.0932, 0.1432))
    assert np.median(err) <= 1.5 * 0.005  # 1.5 x the poses' own scatter


def _scaled_copy(src, dst, scale: float) -> None:
    """``src`` with every photo and mask resized by ``scale``, the intrinsics and the pane outlines with
    them (pixel indices: the centre of the top-left pixel is 0)."""
    import cv2

    cams = json.loads((src / "cameras.json").read_text())
    panes = json.loads((src / "panes.json").read_text())
    for sub in ("images", "masks"):
        (dst / sub).mkdir(parents=True)
    for stem, c in cams.items():
        W, H = round(c["width"] * scale), round(c["height"] * scale)
        sx, sy = W / c["width"], H / c["height"]
        photo = cv2.imread(str(src / "images" / f"{stem}.jpg"))
        small = cv2.resize(photo, (W, H), interpolation=cv2.INTER_AREA)
        cv2.imwrite(str(dst / "images" / f"{stem}.jpg"), small, [cv2.IMWRITE_JPEG_QUALITY, 95])
        mask = cv2.imread(str(src / "masks" / f"{stem}.png"), cv2.IMREAD_GRAYSCALE)
        mask = cv2.resize(mask, (W, H), interpolation=cv2.INTER_AREA)
        cv2.imwrite(str(dst / "masks" / f"{stem}.png"), np.where(mask > 127, 255, 0).astype(np.uint8))
        K = np.array(c["K"], float)
        K[0] *= sx
        K[1] *= sy
        K[0, 2], K[1, 2] = (c["K"][0][2] + 0.5) * sx - 0.5, (c["K"][1][2] + 0.5) * sy - 0.5
        c.update(K=K.tolist(), width=W, height=H)
        panes[stem] = [[[(x + 0.5) * sx - 0.5, (y + 0.5) * sy - 0.5] for x, y in o] for o in panes[stem]]
    (dst / "cameras.json").write_text(json.dumps(cams))
    (dst / "panes.json").write_text(json.dumps(panes))


def test_the_same_photos_at_a_smaller_size_give_the_same_panels(gcw, tmp_path):
    """Lengths follow the facade, not the pixels: the photos at 0.6 of their size, a coarser ground sample
    distance, give the same frames (the same frame depth, here none: these frames show no parallax a
    view's few bars could tell from their scatter) and the same corners in the full-size photos' pixels;
    no photo loses more than 0.05 of its mask IoU (img058's empty unit, whose shaded ceiling edge lies one
    pitch beyond its top transom, was taken for an outer transom at 0.6: ``frames.glass_side``)."""
    layout, per_photo = gcw
    src = tmp_path / "small"
    _scaled_copy(SRC, src, 0.6)
    env = {**os.environ, "TQDM_DISABLE": "1"}
    out = subprocess.run([sys.executable, str(REPO / "scripts" / "make_gcw_building.py"), str(src),
                          "--building", "gcw_dev", "--data-root", str(tmp_path / "data")], cwd=REPO, env=env,
                         capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    doit(["segment_panels", "building=gcw_dev"], env, tmp_path / "data")
    small = BuildingLayout(tmp_path / "data", "gcw_dev")
    depth = read_manifest(small, "segment_panels").metrics["frame_depth_m"]
    assert depth == read_manifest(layout, "segment_panels").metrics["frame_depth_m"]
    small_per_photo = evaluate_building(small, src)
    s, full = summary(small_per_photo), summary(per_photo)
    assert s["found_fraction"] >= 0.9 and s["mask_iou_median"] >= full["mask_iou_median"] - 0.03
    assert s["corner_error_median_px"] / 0.6 <= 1.2 * full["corner_error_median_px"]
    for stem, r in per_photo.items():
        assert small_per_photo[stem]["mask_iou"] >= r["mask_iou"] - 0.05, stem


def test_the_same_photos_of_a_wall_25_times_the_size_give_the_same_masks_and_panels(gcw, tmp_path):
    """One config for any scale: the same photos with the poses and the coarse mesh 25 times the size (a
    full-size wall, ``make_gcw_building.py --scale``) give the same masks and the same 3D panels, 25 times
    the size, with the same config: every length of the geometry half is a fraction of one the data gives
    (the frontal views' footprint, the panel pitch the survey finds), which is 25 times the size too."""
    layout, per_photo = gcw
    env = {**os.environ, "TQDM_DISABLE": "1"}
    out = subprocess.run([sys.executable, str(REPO / "scripts" / "make_gcw_building.py"), str(SRC),
                          "--building", "gcw_dev", "--data-root", str(tmp_path), "--scale", "25"], cwd=REPO,
                         env=env, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    doit(["regularize_corners", "building=gcw_dev"], env, tmp_path)
    big = BuildingLayout(tmp_path, "gcw_dev")
    pitch = [read_manifest(lay, "segment_panels").metrics["pitch_unit_m"] for lay in (layout, big)]
    assert pitch[1] == pytest.approx(25 * pitch[0], rel=1e-6)
    s, full = summary(evaluate_building(big, SRC)), summary(per_photo)
    assert s["found"] == full["found"]
    cams = json.loads((SRC / "cameras.json").read_text())
    for stem in per_photo:
        W, H = cams[stem]["width"], cams[stem]["height"]
        seg = [ViewSegmentation.load(lay, stem, W, H).mask for lay in (layout, big)]
        assert iou(*seg) >= 0.99, stem
    panels = [json.loads(lay.path("regularize_panels").read_text())["panels"] for lay in (layout, big)]
    corners = [np.array([p["corners"] for p in ps], float).reshape(-1, 3) for ps in panels]
    assert len(corners[1]) == len(corners[0]) > 0
    # each corner of the full-size wall, brought back to 1:25, lies on one of the model's (within 0.1 mm)
    gap = np.linalg.norm(corners[1][:, None] / 25 - corners[0][None], axis=2).min(axis=1)
    assert gap.max() < 1e-4


#: brighter than taken, a further 10-30 % of these photos' pixels clip (21-34 % already do). At +0.5 EV 15 of
#: 15 whole panes, mask IoU median 0.943, min 0.631; at +1 EV 15 of 15, 0.935 / 0.634 (benchmarks/RESULTS.md;
#: the empty unit clipped pink, near the frames' white, no longer carries the mullions into a border strip:
#: ``EdgeLine.short``; img042's top transom, clipped with the sky beside it, is placed by the grid at its
#: pitch, not at the empty unit's lit ceiling a quarter of a pitch lower: ``grid._with_end_bays``; img060's
#: top strip, which holds the grid's next transom's place and no transom, takes only the mullions that
#: continue on their own, not the two whose centre lines cross the unit's ceiling clipped to the frames'
#: white: ``openings.openings``; img059's top transom, clipped with the unit's lit shelf above it, is widened
#: from its shaded underside on the side the building's pitch puts it: ``frames.widen_narrow_bars``;
#: img052's mullion beside the unit not installed, its centre line clipped with the unit's lit box, carries
#: an opening only on the side whose half shows the frame: ``openings.continues``; img056's top transom,
#: its upper edge between clipped pixels but where the lit shelf slants away, keeps the slope of its lower
#: edge: ``edges.bar_edges``; img060's transom over the set-off unit alone, found thin across the view and
#: joined to a front face that shows the empty unit's pink ceiling beside it, bounds no pane there:
#: ``openings._not_a_pane``; img059's top transom, clipped with the lit shelf above it, is not joined from
#: the line along its glass side to a front face in the glass below: ``frames.widen_narrow_bars``; img050's
#: top strip over the empty unit's ceiling is stopped by the mullion beside it, whose centre line, a fringe
#: clipped in one run with the glass beside it, mirroring the sky, tells nothing of the frame:
#: ``EdgeLine.clip_beyond``).
#: What is lost at +1 EV: the frames and the bright glass beside them meet at full scale, where no edge is
#: left to find (img041's second mullion, clipped with the empty unit's lit box beside it, is found only at
#: the building's pitch, where an edge between two clipped pixels counts as unknown: the view's own search
#: takes the grey glass beside the frame; img042's top transom has its far edge outside the view and its
#: near edge between clipped pixels over the left pane, too little for the grid to take it, and is placed
#: at its pitch where the mullions go on across the strip beyond: ``frames.with_clipped_ends``' ``cut``;
#: img043's last mullion, clipped and cut by the view's border, keeps its pane where its far edge, unknown
#: in every row, is placed at the bar's width: ``edges.bar_edges``; img060's lowest transom, clipped, is
#: missed by the first transom pass, and the mullions are sought again over the run the colour prior
#: finds: ``frames._runs_beyond``); the empty unit's shelves and ceiling clip to the frames' white: its
#: cell passes the transoms' colour prior and is taken for a pane; the median, 0.935, is 0.016 under the
#: photos' as taken. img050's top strip over the empty unit's ceiling, carried in the median by a mullion
#: whose centre line, clipped in one run with the glass beside it mirroring the sky, reads as the frame,
#: stops beside that mullion (``EdgeLine.clip_beyond``: 0.773 -> 0.951). The frames' depth is not
#: measured at +1 EV: one view's mullions, widened alike by the glass clipped beside them, fit a slope of
#: 4 mm alone, which counts only where other views agree (``building.building_frame_parallax_m``); with it
#: every view's corners moved by several px (the median 0.894, corners 5.1 px against 4.0).
#: At -0.5 EV one of img042's whole panes
#: is close to being marked occluded: its side along the mullion beside the empty unit shows the frame's
#: colour or its edge over about 0.6 of its length, the 0.6 needed (``openings.MIN_EDGE_SUPPORT``)


@pytest.fixture(scope="module")
def exposed(gcw, tmp_path_factory):
    """{name: (truth folder, data root)} of the photos at each of ``EXPOSURES``, run through
    segment_panels with the same config."""
    tmp = tmp_path_factory.mktemp("exposed")
    env = {**os.environ, "TQDM_DISABLE": "1"}
    roots = {}
    for i, (name, gains) in enumerate(EXPOSURES.items()):
        src = tmp / f"src{i}"
        exposed_copy(SRC, src, gains)
        out = subprocess.run([sys.executable, str(REPO / "scripts" / "make_gcw_building.py"), str(src),
                              "--building", "gcw_dev", "--data-root", str(tmp / f"data{i}")], cwd=REPO,
                             env=env, capture_output=True, text=True)
        assert out.returncode == 0, out.stderr
        roots[name] = (src, tmp / f"data{i}")
    # the variants' DAGs share nothing: run them side by side, as many as there are cores
    names = list(roots)
    for start in range(0, len(names), usable_cores()):
        procs = {n: subprocess.Popen(_cmd(["segment_panels", "building=gcw_dev"], roots[n][1]), cwd=REPO,
                                     env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
                 for n in names[start : start + usable_cores()]}
        for n, proc in procs.items():
            log = proc.communicate(timeout=900)[0]
            assert proc.returncode == 0, f"{n}: {log}"
    return roots


@pytest.mark.parametrize("name", list(EXPOSURES))
def test_the_same_photos_at_another_exposure_and_white_balance_give_the_same_panels(gcw, exposed, name):
    """No decision rests on an absolute brightness or colour: the photos at another exposure or with a
    white balance off by 20 % (one config) find as many whole panes and as much of the glass, within 0.05
    of the photos as taken, with no photo under a mask IoU of 0.5."""
    _, per_photo = gcw
    full = summary(per_photo)
    src, data = exposed[name]
    s = summary(evaluate_building(BuildingLayout(data, "gcw_dev"), src))
    assert abs(s["found_fraction"] - full["found_fraction"]) <= 0.05
    assert abs(s["mask_iou_median"] - full["mask_iou_median"]) <= 0.05
    assert s["mask_iou_min"] >= 0.5


def test_a_transom_clipped_with_the_sky_beside_it_is_placed_by_the_grid(gcw, exposed):
    """Half a stop brighter than taken, img042's top transom clips with the sky beside it: no edge is left
    at its place, and the empty unit's lit ceiling, about a quarter of a pitch lower, is the best bar
    beyond the transoms found. The grid places the transom at its pitch there (``grid._with_end_bays``),
    so that every photo finds the whole panes it finds as taken."""
    _, per_photo = gcw
    src, data = exposed["+0.5 EV"]
    brighter = evaluate_building(BuildingLayout(data, "gcw_dev"), src)
    assert {s: r["n_found"] for s, r in brighter.items()} == {s: r["n_found"] for s, r in per_photo.items()}


def test_a_transom_clipped_with_the_lit_shelf_above_it_is_widened_on_the_side_of_the_pitch(gcw, exposed):
    """Half a stop brighter than taken, img059's top transom clips with the empty unit's lit shelf above
    it, and the grid takes the thin shaded line along its glass side for the bar. Widened to the
    building's width by its edges alone it would go into the glass, where a faint reflected edge is found,
    while its edge in the clip is unknown; the building's pitch from the transom below puts it in the clip
    (``frames.widen_narrow_bars``), its centre line shows the frame across the border strips, and the
    panes cut by the border beside it are kept as taken."""
    _, per_photo = gcw
    src, data = exposed["+0.5 EV"]
    brighter = evaluate_building(BuildingLayout(data, "gcw_dev"), src)
    assert brighter["img059"]["mask_iou"] >= per_photo["img059"]["mask_iou"] - 0.05


def test_a_transom_known_only_where_the_lit_shelf_slants_away_keeps_the_slope_of_its_other_edge(gcw, exposed):
    """Half a stop brighter than taken, img056's top transom clips with the empty unit's lit shelf above
    it: its upper edge lies between clipped pixels but for a short stretch where the shelf's underside
    slants away from it, and a line fitted there alone would climb into the shelf across the border strip
    (the bar's centre line showing the frame over 0.42 of the strip, 1.0 as taken). The edge is made
    parallel to the bar's lower edge (``edges.bar_edges``), and the panes of the strip are kept as taken."""
    _, per_photo = gcw
    src, data = exposed["+0.5 EV"]
    brighter = evaluate_building(BuildingLayout(data, "gcw_dev"), src)
    assert brighter["img056"]["mask_iou"] >= per_photo["img056"]["mask_iou"] - 0.05


def test_a_mullion_clipped_with_the_lit_unit_beside_it_is_found_at_the_buildings_pitch(gcw, exposed):
    """A stop brighter than taken, img041's second mullion clips with the empty unit's lit box beside it
    over most of its length: its edge on that side is unknown, and freely sought the grid takes the grey
    glass beside the frame for the mullion, and no transoms pass the colour prior against it. Sought again
    at the building's pitch across the mullions, where an edge between two clipped pixels is unknown, not
    absent, the frame is found, and the photo as much of its glass as taken."""
    _, per_photo = gcw
    src, data = exposed["+1 EV"]
    brighter = evaluate_building(BuildingLayout(data, "gcw_dev"), src)
    assert brighter["img041"]["mask_iou"] >= per_photo["img041"]["mask_iou"] - 0.05



def test_a_transom_over_a_set_off_unit_alone_bounds_no_pane_over_the_empty_unit_beside_it(gcw, exposed):
    """A stop brighter than taken, img060's transom over the unit set off its neighbours (the empty unit
    beside it runs higher) is found across the whole view as a thin line: over the set-off unit the
    glass's edge under the clipped frame, over the empty unit the back edge of its lit ceiling. Joined to
    the front face above it, that face shows the frames' white (clipped) over the set-off unit and the
    ceiling's pink over the empty one, where no mullion beside the cells shows an edge: those cells, and the
    strip above them, are no panes (``openings._not_a_pane``), and the photo keeps a mask IoU of 0.5."""
    src, data = exposed["+1 EV"]
    brighter = evaluate_building(BuildingLayout(data, "gcw_dev"), src)
    assert brighter["img060"]["mask_iou"] >= 0.5


def test_a_line_under_a_transom_clipped_with_the_lit_shelf_is_not_joined_to_the_glass_below(gcw, exposed):
    """A stop brighter than taken, img059's top transom clips white with the empty unit's lit shelf above
    it, and the grid takes the line along its glass side for the bar, as wide as the side face the
    parallax gives there: joined to a front face beyond it, away from the camera's foot, that face is the
    glass below (neither the frames' white nor a clip over half of it), while the building's pitch puts the
    bar in the clip above, which shows the clip. The bar is found again above the line
    (``frames.widen_narrow_bars``), and the top of the panes below it is the glass's (0.863 with the join)."""
    src, data = exposed["+1 EV"]
    brighter = evaluate_building(BuildingLayout(data, "gcw_dev"), src)
    assert brighter["img059"]["mask_iou"] >= 0.88


def test_a_mullion_clipped_and_cut_by_the_views_border_keeps_its_pane(gcw, exposed):
    """A stop brighter than taken, img043's last mullion clips white, and the view's border slants across
    it: its far edge lies outside the view or between two clipped pixels in every row. Unknown, not
    absent (``edges.bar_edges``), it is placed at the bar's width from the near edge, and the pane beside
    the bar is whole, as in the photo as taken."""
    _, per_photo = gcw
    src, data = exposed["+1 EV"]
    brighter = evaluate_building(BuildingLayout(data, "gcw_dev"), src)
    assert brighter["img043"]["n_found"] == per_photo["img043"]["n_found"] == 2


def test_a_transom_cut_by_the_views_border_and_clipped_with_the_glass_is_placed_by_the_grid(gcw, exposed):
    """A stop brighter than taken, img042's top transom has its far edge outside the view and its near
    edge between two clipped pixels over the left pane (the sky reflected there clips): the view shows
    nothing of it either way. The mullions go on across the strip beyond the transoms found, so the
    facade does: the grid places the transom at its pitch (``frames.with_clipped_ends``' ``cut``), and the
    photo finds the whole panes it finds as taken."""
    _, per_photo = gcw
    src, data = exposed["+1 EV"]
    brighter = evaluate_building(BuildingLayout(data, "gcw_dev"), src)
    assert brighter["img042"]["n_found"] == per_photo["img042"]["n_found"] == 3

def test_mullions_are_sought_over_the_transoms_run_where_the_first_pass_missed_one(gcw, exposed):
    """A stop brighter than taken, img060's lowest transom clips white, the glass above it glares into it
    and the view's border runs below it, and the first transom pass, over the whole width, finds only the
    two that bound the empty unit's row: the mullions, sought over those rows, meet the unit's lit room,
    where the mullion between its two openings does not run, and take the room's post or its side for
    one. The transoms found with the mullions' colour run on to the
    lowest; the mullions are sought again over that whole run (``frames._runs_beyond``), the mullion
    between the lower row's panes is found and the one clipped white beside the view's border placed at
    the pitch, and the photo finds the whole panes it finds as taken."""
    _, per_photo = gcw
    src, data = exposed["+1 EV"]
    brighter = evaluate_building(BuildingLayout(data, "gcw_dev"), src)
    assert brighter["img060"]["n_found"] == per_photo["img060"]["n_found"] == 2


def test_views_off_the_wall_grid_are_listed_with_the_reason(gcw):
    """Nothing silent: every photo whose grid's pitch is not the wall's (0.1032 x 0.1532 m, the truth's;
    a shelf behind an empty unit taken for a transom) is listed in the manifest with its pitch, after the
    building's grid was tried on it; a photo listed has a pitch off the building's."""
    layout, _ = gcw
    m = read_manifest(layout, "segment_panels").metrics
    off = m["views_off_the_building_grid"]
    for stem, v in m["views"].items():
        wrong = [name for name, true in (("x", 0.1032), ("y", 0.1532))
                 if abs(v.get(f"pitch_{name}_m", 0.0) / true - 1.0) > 0.12]
        if wrong and stem not in off:
            pytest.fail(f"{stem}: pitch {wrong} off the wall's, not listed")
        for name in wrong:
            assert f"pitch {name}" in off[stem] and off[stem].endswith("own kept")
    assert set(off) <= set(m["views"])


def test_a_bar_beside_a_unit_not_installed_keeps_its_sides_apart_brighter_or_off_balance(gcw, exposed):
    """img052's top strip mirrors a clipped sky beside a unit not installed: the bar between them goes on
    by its half facing the glass only. Half a stop brighter, or with the white balance off, the unit's lit
    box clips to the frames' white up to the halves' meeting, and the bar's centre line shows the frame's
    colour there; the halves still tell its sides apart, and the photo keeps its glass as taken."""
    _, per_photo = gcw
    for name in ("+0.5 EV", "white balance off by 20 %"):
        src, data = exposed[name]
        other = evaluate_building(BuildingLayout(data, "gcw_dev"), src)
        assert other["img052"]["mask_iou"] >= per_photo["img052"]["mask_iou"] - 0.05, name


def test_a_bar_whose_fitted_edge_lies_on_the_glass_keeps_both_halves_beyond_the_run_darker(gcw, exposed):
    """A stop darker, img051's second mullion shows only one unit's frame over the transoms' run: its
    other half's place, where its fitted edge lies, shows the pane beside it. In the bottom strip the bar
    is whole, and both halves read the frame's colour there: the half that lies on the glass over the run
    is read against the bar's colour, not the glass's, and the strip keeps the glass on both sides of the
    bar."""
    _, per_photo = gcw
    src, data = exposed["-1 EV"]
    other = evaluate_building(BuildingLayout(data, "gcw_dev"), src)
    assert other["img051"]["mask_iou"] >= per_photo["img051"]["mask_iou"] - 0.05


def test_a_cell_beside_a_mullion_without_its_half_is_no_pane_at_every_exposure(gcw, exposed):
    """img042's unit not installed, in its row of complete cells: the mullion between it and the glass
    beside it is placed at its whole width and shows only the glass's unit's half over the cell's rows,
    its other half the unit's lit box. The cell is no pane (``openings._not_a_pane``), as taken and at
    every exposure; a stop darker, img051's unit not installed shows the same beside its other mullion."""
    _, per_photo = gcw
    assert per_photo["img042"]["mask_iou"] >= 0.85
    for name in EXPOSURES:
        src, data = exposed[name]
        assert evaluate_building(BuildingLayout(data, "gcw_dev"), src)["img042"]["mask_iou"] >= 0.85, name
    src, data = exposed["-1 EV"]
    assert evaluate_building(BuildingLayout(data, "gcw_dev"), src)["img051"]["mask_iou"] >= 0.85


def test_a_mullion_found_as_the_half_beside_a_unit_not_installed_keeps_that_unit_out(gcw, exposed):
    """img051's second mullion shows only the glass's unit's half over its unit not installed (the pane
    beyond it clipped white), found thin there and widened onto the unit's box: read on the bar that half
    belongs to, the half toward the unit is gone and its cell is no pane (``frames._halves_at_place``), as
    taken and half a stop either way."""
    _, per_photo = gcw
    assert per_photo["img051"]["mask_iou"] >= 0.8
    for name in ("-0.5 EV", "+0.5 EV"):
        src, data = exposed[name]
        assert evaluate_building(BuildingLayout(data, "gcw_dev"), src)["img051"]["mask_iou"] >= 0.8, name


def test_a_mullion_found_at_the_width_of_the_half_beside_a_unit_not_installed_keeps_it_out(gcw, exposed):
    """img049's right mullion beside its unit not installed is found at the width of the half that is
    there (7.6 working px, the building's 10.7), kept at that width, both its halves on that half. The
    building's pitch puts the bar's centre beyond it on the unit's side: read on the bar of the building's
    width that holds it as its half away from the unit, the half toward the unit is gone, and the unit's
    cell is no pane (``frames._halves_at_place``), as taken and at every exposure (0.629 as taken with the
    cell kept). The same bar bounds the strip the top border cuts above it, over the unit above, not
    installed either: read so over the strip's rows in the view, it is no pane either (0.773 as taken with
    the strip kept, 0.858 without; ``openings._not_a_pane``), nor is img051's strip over its unit beside a
    mullion read so (0.824 as taken with it kept, 0.882 without)."""
    _, per_photo = gcw
    assert per_photo["img049"]["mask_iou"] >= 0.83
    assert per_photo["img051"]["mask_iou"] >= 0.86
    for name in EXPOSURES:
        src, data = exposed[name]
        assert evaluate_building(BuildingLayout(data, "gcw_dev"), src)["img049"]["mask_iou"] >= 0.83, name


def test_a_mullion_found_at_the_width_of_the_half_is_read_where_the_view_shows_its_bar_whole(gcw, exposed):
    """img041's left mullion beside its unit not installed is found at the width of the half that is
    there (5.6 working px, the building's 10.7) and kept; the only other mullion is found 17.8 px wide over
    the unit's side wall, so the building's pitch from it puts the bar within a quarter of the missing half
    of the line. Below the bottom transom both the bar's neighbours are glazed and it is found whole, on the
    unit's side of the line: read on the bar of the building's width that holds the line as its half away
    from the unit, the half toward the unit is gone, and the unit's cell is no pane
    (``frames._place_beyond``), as taken and at every exposure (0.575 as taken with the cell kept)."""
    _, per_photo = gcw
    assert per_photo["img041"]["mask_iou"] >= 0.68
    for name in EXPOSURES:
        src, data = exposed[name]
        assert evaluate_building(BuildingLayout(data, "gcw_dev"), src)["img041"]["mask_iou"] >= 0.68, name


def test_a_border_strip_beyond_its_units_top_is_read_where_its_mullion_shows_a_half(gcw, exposed):
    """img041's top strip runs over its unit not installed and, beyond the glazed units' top, over the
    row above, not installed on either side of its left mullion: that mullion (found at the width of the
    half that is there, read at its place) shows its half away from the strip over the glazed unit's rows
    alone (0.48-0.49 of the strip's rows in the view) and its half facing it nowhere; the other mullion is
    fitted 1.5 times its family's width there, inside a run clipped white twice the building's bar wide
    (the boxes' walls), both its halves on it. Read over the rows where the left mullion shows either
    half, the strip is no pane (``openings._halves_told``), as taken and at every exposure (0.697 as taken
    with the strip kept)."""
    _, per_photo = gcw
    assert per_photo["img041"]["mask_iou"] >= 0.76
    for name in EXPOSURES:
        src, data = exposed[name]
        assert evaluate_building(BuildingLayout(data, "gcw_dev"), src)["img041"]["mask_iou"] >= 0.76, name


def test_a_unit_not_installed_in_a_border_strip_the_median_carries_holds_no_glass(gcw):
    """img043's top strip runs over a unit not installed, its grey ceiling beside a mullion that shows
    only the glazed unit's half there; the strip's other mullions carry it in the median, the ceiling's
    opening holds no panel. img049's bottom strip has a mullion fitted half as wide again as its family's
    there (its low edge on the glass beside the frame): its low half, read off the frame, is not taken for
    gone, and the glass beside it stays."""
    _, per_photo = gcw
    assert per_photo["img043"]["mask_iou"] >= 0.9
    assert per_photo["img049"]["mask_iou"] >= 0.62


def test_a_mullions_centre_line_clipped_with_the_glass_beside_it_carries_no_unit_not_installed(gcw, exposed):
    """A stop brighter than taken, img050's top strip runs over the empty unit's grey ceiling, carried in
    the median by its two mullions' centre lines clipped white. The left one's is a fringe between its half
    on the glass's side and the ceiling, clipped in one run with the glass beyond, which mirrors the sky:
    it tells nothing of the frame (``EdgeLine.clip_beyond``), its half facing the ceiling is gone and its
    edges are weak there, and the ceiling's opening holds no panel (0.773 with the fringe read as the
    frame)."""
    src, data = exposed["+1 EV"]
    brighter = evaluate_building(BuildingLayout(data, "gcw_dev"), src)
    assert brighter["img050"]["mask_iou"] >= 0.9
