"""Geometry: transforms, cameras, alignment. Z-up world, OpenCV cameras, T_a_b names."""
