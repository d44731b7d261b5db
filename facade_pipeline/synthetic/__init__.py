"""The synthetic facade simulator: ray-traced glass facades with near-field reflections and ground truth.

Modules: ``params`` (the ``[synthesize]`` config), ``facade`` (parts, panels, true meshes), ``environment``
(the near field), ``textures`` (procedural albedo, sky, sun), ``render`` (ray casting, Eq. 7-8), ``cameras``
(UAV and frontal views, pose noise), ``coarse`` (photogrammetry-like mesh and points), ``simulate`` (putting
it together). Only declared effects are computed; everything is deterministic for a seed.
"""

from facade_pipeline.synthetic.params import ALL_EFFECTS, SynthesizeParams

__all__ = ["ALL_EFFECTS", "SynthesizeParams"]
