"""Stage `bake_normals`: per training view, normal, depth and facade/glass masks ray-cast from the
corrected mesh."""
