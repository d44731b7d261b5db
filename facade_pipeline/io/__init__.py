"""Reading and writing: atomic files, COLMAP models, meshes, images, EXR maps, manifests."""
