"""Exposure of a view taken out before its frames are sought.

Every colour threshold of the segmentation (``uniformity_scale``, ``frame_colour_scale``,
``frame_colour_tol``, LSD's gradient threshold) is a distance between colours. A camera's exposure
multiplies linear light by a gain, which the encoding (a power law, near enough) turns into a gain of the
encoded values: every such distance in a view would scale with it. The view is therefore scaled by one gain
so that its brightest part (the ``BRIGHT_QUANTILE`` of the pixels that show the view, in its brightest
channel) sits at full scale: the thresholds then count in the view's own range, whatever the exposure. A
view already at full scale there (sunlit frames or highlights, as most photos of glass have) is left as it
is, and a view darker by any gain is brought back to it. One gain for the three channels: a gain per
channel would also undo a white balance, but it recolours every view whose brightest part is not white
(a blue sky reflected), and the frames' colour against the glass is evidence (``frame_colour_scale``).
"""

from __future__ import annotations

import numpy as np

#: a view's brightest part, which is set to full scale: the quantile of the view's pixels, high enough to be
#: the brightest surfaces (sky reflected, sunlit frames), low enough that a few specular pixels do not set it
BRIGHT_QUANTILE = 0.99


def normalise_exposure(image: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    """The RGB uint8 image [H, W, 3] scaled by one gain (never darkened) so that the ``BRIGHT_QUANTILE`` over
    the ``valid`` pixels [H, W] (all where None) of its brightest channel is 255, clipped to 255; the image
    itself where it is there already."""
    pixels = image.reshape(-1, image.shape[2]) if valid is None else image[np.asarray(valid, bool)]
    if not len(pixels):
        return image
    bright = float(np.quantile(pixels, BRIGHT_QUANTILE, axis=0).max())
    gain = 255.0 / max(bright, 1.0)
    if gain <= 1.0:
        return image
    return np.minimum(np.rint(image * np.float32(gain)), 255.0).astype(np.uint8)
