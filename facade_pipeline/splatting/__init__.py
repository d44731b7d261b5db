"""Differentiable 2D Gaussian Splatting (surfel) renderer: ``render_2dgs`` with an exact pure-torch backend,
a compiled C++/OpenMP CPU backend and an optional gsplat CUDA backend."""

from facade_pipeline.splatting.render import render_2dgs, resolve_backend
from facade_pipeline.splatting.types import Backend, PixelWindow, SurfelRender

__all__ = ["Backend", "PixelWindow", "SurfelRender", "render_2dgs", "resolve_backend"]
