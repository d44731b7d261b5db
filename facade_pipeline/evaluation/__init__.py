"""Evaluation: image metrics over a mask (PSNR, SSIM, LPIPS) and geometry metrics against a true mesh.

``metrics`` holds PSNR, SSIM and the geometry helpers (numpy, float64); ``lpips`` the LPIPS network of our
own, built from a weights file; ``lpips_convert`` turns the upstream Flax checkpoints into that file.
"""
