"""Reconstruction: camera poses with metric scale and dynamic 3D Gaussians."""
