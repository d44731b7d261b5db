"""Deferred shading of reflective glass (the paper's Eq. 7-10): spherical-harmonics diffuse colour, Schlick
Fresnel, reflection direction and surface point from rendered normal and depth, and the reflection models
(``sh``, ``envmap``, ``mlp``) that give the specular colour R."""
