"""Reflection-aware 2D Gaussian Splatting training (the paper's section 3.2): the Gaussian model, its
initialisation, losses and schedules, densification, the optimisers, what a step looks at (``batches.py``),
the checkpoint file (``checkpoints.py``), the trainer's loop (``trainer.py``: build / step / train), the PLY
export and the trained model's files (``trained.py``, the train_gs hand-off). Measuring a trained model
belongs to the evaluation package, which builds on this one. The rasterizer is ``facade_pipeline.splatting``;
shading is ``facade_pipeline.shading``."""
