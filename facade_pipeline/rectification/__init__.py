"""Stage `rectify`: a plane or vertical cylinder fitted to the coarse points a frontal view sees, and the
exact maps between the view and a metric, fronto-parallel image of that surface."""
