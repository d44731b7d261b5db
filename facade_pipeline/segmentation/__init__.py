"""Glass-panel segmentation of frontal views: line segments, MAP panel grid, panels and masks."""
