"""Cleaning a user's coarse mesh with MeshLab's filters (pymeshlab) before anything casts rays on it.

Photogrammetry and Poisson meshes come with vertices repeated along tile seams, faces listed twice and faces
of zero area; ray casting drops the degenerate ones silently and a repeated face is hit twice. The filters
merge exactly coincident vertices, then drop duplicate faces, faces with a repeated vertex or zero area,
and vertices no face uses. Geometry is unchanged: every remaining face keeps its corners.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pymeshlab

from facade_pipeline.io.meshes import make_mesh

FILTERS = (
    "meshing_remove_duplicate_vertices",
    "meshing_remove_duplicate_faces",
    "meshing_remove_null_faces",
    "meshing_remove_unreferenced_vertices",
)


def clean_mesh(mesh: o3d.geometry.TriangleMesh) -> tuple[o3d.geometry.TriangleMesh, dict[str, int]]:
    """The cleaned mesh (vertex colours kept) and how many vertices and faces it lost."""
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    colors = np.asarray(mesh.vertex_colors) if mesh.has_vertex_colors() else None
    kwargs = {} if colors is None else {"v_color_matrix": np.c_[colors, np.ones(len(colors))]}
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=v, face_matrix=f, **kwargs))
    for name in FILTERS:
        getattr(ms, name)()
    out = ms.current_mesh()
    cv, cf = out.vertex_matrix(), out.face_matrix()
    cleaned = make_mesh(cv, cf, None if colors is None else out.vertex_color_matrix()[:, :3])
    return cleaned, {"vertices_removed": len(v) - len(cv), "faces_removed": len(f) - len(cf)}
