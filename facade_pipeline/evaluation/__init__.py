"""Evaluation: image metrics over a mask (PSNR, SSIM, LPIPS) and geometry metrics against a true mesh.

``core`` is the one measurement of a trained model on views (train_gs's held-out check, the evaluate
stage, the benchmarks), over the regions of ``image_eval``; ``building`` is what the evaluate stage runs
on a building (its models, splits, geometry, metrics.json and the report); ``render_views`` loads and
renders a trained model. ``metrics`` holds PSNR, SSIM and the geometry helpers (float64); ``lpips`` the
LPIPS network of our own, built from a weights file; ``lpips_convert`` turns the upstream Flax checkpoints
into that file.
"""
