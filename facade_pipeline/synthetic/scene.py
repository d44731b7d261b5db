"""The whole synthetic scene: facade parts, panels, the environment, and one triangle soup to ray-cast.

Triangle ids of ``Scene.mesh`` follow the order facade (glass, then frames, part by part), body walls,
environment, so ``material`` / ``object_id`` lookups by primitive id are direct.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from facade_pipeline.synthetic.environment import Placement, environment_mesh, place_objects, site_frame
from facade_pipeline.synthetic.facade import (
    Panel,
    PartGeometry,
    Room,
    build_panels,
    draw_room,
    part_meshes,
    world_from_facade,
)
from facade_pipeline.synthetic.mesh import Material, TriMesh, concat
from facade_pipeline.synthetic.noise import rng_for
from facade_pipeline.synthetic.params import SynthesizeParams

SITE_MARGIN_M = 10.0  # trees are placed this far beyond the facade's extent along site x (m)


@dataclass(frozen=True, eq=False)
class Scene:
    """Everything the renderer and the writers need. ``panel_diffuse`` [P, 3] is indexed by the glass
    triangles' object id; ``world_from_site`` [4, 4] is the environment's frame; ``rooms`` are the rooms
    behind the unglazed units, indexed by their triangles' object id // ``ROOM_OBJECTS``."""

    params: SynthesizeParams
    parts: tuple[PartGeometry, ...]
    panels: tuple[Panel, ...]
    glass: TriMesh
    frames: TriMesh
    body: TriMesh
    environment: TriMesh
    mesh: TriMesh
    world_from_site: np.ndarray
    placement: Placement
    rooms: tuple[Room, ...] = ()

    @property
    def panel_diffuse(self) -> np.ndarray:  # [P, 3]
        return np.array([p.diffuse for p in self.panels])

    @property
    def facade(self) -> TriMesh:
        """The true facade mesh: glass and frames (the body walls are not facade)."""
        return concat([self.glass, self.frames])

    def site_xy(self, world: np.ndarray) -> np.ndarray:
        """Site-frame (x, y) [N, 2] of world points [N, 3]."""
        T = self.world_from_site
        return ((world - T[:3, 3]) @ T[:3, :3])[:, :2]


def build_scene(params: SynthesizeParams) -> Scene:
    """Build the scene of ``params`` (deterministic for ``params.seed``)."""
    style = params.facade
    parts = tuple(
        PartGeometry(i, p, world_from_facade(p), style.frame_width_m) for i, p in enumerate(params.parts)
    )
    rng = rng_for(params.seed, "interior")
    room_rng = rng_for(params.seed, "rooms")
    panels: list[Panel] = []
    rooms: list[Room] = []
    glass, frames, bodies = [], [], []
    for geom in parts:
        unglazed = frozenset((r, c) for k, r, c in style.unglazed_units if k == geom.index)
        drawn = {(r, c): draw_room(geom, style, r, c, room_rng) for r, c in sorted(unglazed)}
        g, f, b = part_meshes(geom, style, len(panels), 0.0, drawn, len(rooms))
        panels.extend(build_panels(geom, style, rng, unglazed))
        rooms.extend(drawn.values())
        glass.append(g)
        frames.append(f)
        bodies.append(b)
    T = site_frame(params.parts)
    half_span = _half_span(parts, T) + SITE_MARGIN_M
    masts = rng_for(params.seed, "masts") if params.has("masts_and_cranes") else None
    placement = place_objects(params.environment, half_span, rng_for(params.seed, "placement"), masts)
    env = environment_mesh(params.environment, T, placement)
    g, f, b = concat(glass), concat(frames), concat(bodies)
    mesh = concat([g, f, b, env])
    assert int((mesh.material == Material.GLASS).sum()) == len(g.triangles)
    return Scene(params, parts, tuple(panels), g, f, b, env, mesh, T, placement, tuple(rooms))


def _half_span(parts: tuple[PartGeometry, ...], T: np.ndarray) -> float:
    ends = np.concatenate(
        [
            g.surface(np.array([-g.part.width_m / 2, g.part.width_m / 2]), np.zeros(2), np.zeros(2))
            for g in parts
        ]
    )
    return float(np.abs((ends - T[:3, 3]) @ T[:3, 0]).max())


def scene_description(scene: Scene) -> dict:
    """The scene as built, for gt/scene.json (JSON-ready)."""
    p = scene.params
    parts = []
    for g in scene.parts:
        d = {
            "index": g.index,
            "name": g.part.name,
            "kind": g.part.kind,
            "world_from_facade": g.world_from_facade.tolist(),
            "width_m": g.part.width_m,
            "height_m": g.part.height_m,
            "rows": g.part.rows,
            "cols": g.part.cols,
            "mullion_s_m": g.s_lines.tolist(),
            "transom_z_m": g.z_lines.tolist(),
        }
        if g.part.kind == "cylindrical":
            axis = g.world_from_facade[:3, 3] - g.part.radius_m * g.world_from_facade[:3, 1]
            d.update(
                radius_m=g.part.radius_m,
                arc_deg=float(np.degrees(g.part.width_m / g.part.radius_m)),
                axis_point=axis.tolist(),
                axis_direction=[0.0, 0.0, 1.0],
            )
        parts.append(d)
    return {
        "conventions": {
            "units": "metres, world z up",
            "facade_frame": "x = y cross z (+x is to the LEFT of a viewer outside), y outward normal, z up",
            "surface_coords": "s along the glass left to right seen from outside (arc length on cylinders), "
            "z up, h along the outward normal; planar (x, y, z) = (-s, h, z)",
            "panel_corners": "bottom-left, bottom-right, top-right, top-left as seen from outside",
        },
        "effects": list(p.effects),
        "seed": p.seed,
        "parts": parts,
        "facade": {k: getattr(p.facade, k) for k in p.facade.__dataclass_fields__},
        "materials": {m.name.lower(): int(m) for m in Material},
        "environment": {
            "world_from_site": scene.world_from_site.tolist(),
            "buildings_site_x_y_width_depth_height_yaw": [list(b) for b in scene.placement.buildings],
            "trees_site_x_y_height": [list(t) for t in scene.placement.trees],
            **(
                {
                    "poles_site_x_y_height": [list(t) for t in scene.placement.poles],
                    "crane_site_x_y_height_jib": list(scene.placement.crane),
                }
                if p.has("masts_and_cranes")
                else {}
            ),
            "params": {k: getattr(p.environment, k) for k in p.environment.__dataclass_fields__},
        },
        "triangles": {
            "glass": len(scene.glass.triangles),
            "frames": len(scene.frames.triangles),
            "body": len(scene.body.triangles),
            "environment": len(scene.environment.triangles),
        },
    }


def panels_description(scene: Scene) -> dict:
    """The true panels, for gt/panels.json (JSON-ready): the glazed units under ``panels``; with
    "unglazed_units", the units without glass under ``openings``, in the same form (not panels: the
    segmentation should not find them)."""

    def entry(pn) -> dict:
        return {
            "part": scene.parts[pn.part].part.name,
            "part_index": pn.part,
            "row": pn.row,
            "col": pn.col,
            "corners": pn.corners.tolist(),
            "normal": pn.normal.tolist(),
        }

    out = {
        "corner_order": "bottom-left, bottom-right, top-right, top-left as seen from outside",
        "panels": [entry(pn) for pn in scene.panels if pn.glazed],
    }
    if scene.params.has("unglazed_units"):
        out["openings"] = [entry(pn) for pn in scene.panels if not pn.glazed]
    return out
