"""Reflection-aware 2D Gaussian Splatting training (the paper's section 3.2): the Gaussian model, its
initialisation, losses and schedules, densification, the trainer (build / step / evaluate / checkpoint) and
the PLY export. The rasterizer is ``facade_pipeline.splatting``; shading is ``facade_pipeline.shading``."""
