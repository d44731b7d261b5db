"""Geometry: cameras, frames, transforms."""
