"""Stage `import_photogrammetry`: checks that the cameras and the coarse mesh describe one scene."""
