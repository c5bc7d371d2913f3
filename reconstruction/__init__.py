"""Reconstruction: camera poses with metric scale, a differentiable Gaussian rasterizer, and dynamic 3D Gaussians.

The public surface; `poses` is imported on use (it loads pycolmap).
"""
from .dynamic import FitSettings, Trajectory, fit_dynamic, fit_static
from .gaussians import Gaussians, load_ply, save_ply
from .raster import RasterOutput, gsplat_available, rasterize, rasterize_reference
from .run import DynamicScene, ReconstructResult, ReconstructSettings, reconstruct, render_sequence, train
from .views import Camera, SceneFrame, TrainView, ViewSet, load_views

__all__ = ["Camera", "DynamicScene", "FitSettings", "Gaussians", "RasterOutput", "ReconstructResult",
           "ReconstructSettings", "SceneFrame", "Trajectory", "TrainView", "ViewSet", "fit_dynamic", "fit_static",
           "gsplat_available", "load_ply", "load_views", "rasterize", "rasterize_reference", "reconstruct",
           "render_sequence", "save_ply", "train"]
