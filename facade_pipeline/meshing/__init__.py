"""Mesh operations: the geometric correction of the coarse facade mesh with the 3D panels (the paper,
section 3.1.3) and the surface metrics that compare meshes with a synthetic building's truth."""
