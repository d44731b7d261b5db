"""Stage `regularize_corners`: the 3D panel model (PanelSet, the 04 hand-off), corner observations of the
segmented views lifted onto the coarse mesh, and their regularisation into rows and columns."""
