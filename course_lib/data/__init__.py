"""Loaders and writers: P3 matching folders, COLMAP text models, Blender NeRF data, synthetic scenes."""
