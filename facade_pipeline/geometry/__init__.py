"""The shared geometry core: cameras and frames, ray casting on meshes, polynomial warps. Every stage's
algorithm package builds on it; it imports none of them."""
