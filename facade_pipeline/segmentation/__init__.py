"""Glass-panel segmentation of frontal views: line segments, MAP panel grid, frame bars, panels and masks."""
