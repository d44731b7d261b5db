"""Exposure and white balance of a view taken out before its frames are sought.

Every colour threshold of the segmentation (``uniformity_scale``, ``frame_colour_scale``,
``frame_colour_tol``, LSD's gradient threshold) is a distance between colours. A camera's exposure and white
balance multiply each channel of linear light by a gain, which the encoding (a power law, near enough) turns
into a gain per channel of the encoded values: every such distance in a view would scale with it. Each
channel of the view is therefore scaled so that its brightest part (the ``BRIGHT_QUANTILE`` of the pixels
that show the view) sits at full scale: the thresholds then count in the view's own range, whatever the
exposure. A channel already clipped there (a view with sunlit frames or highlights, as most photos of glass
are) is left as it is, and a view darker by any gain is brought back to it.
"""

from __future__ import annotations

import numpy as np

#: a channel's brightest part, which is set to full scale: the quantile of the view's pixels, high enough to
#: be the brightest surfaces (sky reflected, sunlit frames), low enough that a few specular pixels do not
#: set it
BRIGHT_QUANTILE = 0.99


def normalise_exposure(image: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    """The RGB uint8 image [H, W, 3] with each channel scaled (never darkened) so that its
    ``BRIGHT_QUANTILE`` over the ``valid`` pixels [H, W] (all where None) is 255, clipped to 255; the
    image itself where no channel needs it."""
    pixels = image.reshape(-1, image.shape[2]) if valid is None else image[np.asarray(valid, bool)]
    if not len(pixels):
        return image
    bright = np.quantile(pixels, BRIGHT_QUANTILE, axis=0)
    gain = 255.0 / np.maximum(bright, 1.0)
    if (gain <= 1.0).all():
        return image
    gain = np.maximum(gain, 1.0)
    return np.minimum(np.rint(image * gain.astype(np.float32)), 255.0).astype(np.uint8)
