"""facade-pipeline: reflective glass facades from UAV photos to a 2D Gaussian Splatting digital twin.

The library: pure functions over arrays and tensors, grouped by domain. Stages in ``stages/`` orchestrate it.
"""

__version__ = "0.1.0"
