"""Reconstruction: camera poses with metric scale, a differentiable Gaussian rasterizer, and dynamic 3D Gaussians.

The public surface. Two stages live here, each with its entry: `run_poses(capture, PoseSettings) -> PoseResult`
(derived/poses.json, points.npz) and `run(capture, ReconstructSettings) -> ReconstructResult` (alias
`reconstruct`; derived/reconstruction/). pycolmap is loaded only when poses are estimated.
"""
from .dynamic import FitSettings, Trajectory, fit_dynamic, fit_static
from .gaussians import Gaussians, load_ply, save_ply
from .linear import LinearSettings
from .modal import ModalSettings
from .model import (
    DynamicScene,
    MotionRecord,
    ReconstructResult,
    ReconstructSettings,
    camera_path,
    check_camera_spec,
    default_source,
    parse_times,
    reconstruct,
    render_sequence,
    train,
    working_width,
)
from .pose_result import PoseResult, PoseSettings
from .poses import estimate_poses, run_poses
from .quaternion import quat_from_rotvec, quat_multiply  # noqa: F401  (exported: the viewer turns Gaussians)
from .raster import RasterOutput, gsplat_available, rasterize, rasterize_image, rasterize_reference
from .views import Camera, SceneFrame, TrainView, ViewSet, load_views

run = reconstruct  # the reconstruct stage's entry

__all__ = ["Camera", "DynamicScene", "FitSettings", "Gaussians", "LinearSettings", "ModalSettings", "MotionRecord",
           "PoseResult", "PoseSettings", "RasterOutput", "ReconstructResult", "ReconstructSettings", "SceneFrame",
           "Trajectory", "TrainView", "ViewSet", "camera_path", "check_camera_spec", "default_source", "estimate_poses",
           "fit_dynamic",
           "fit_static", "gsplat_available", "load_ply", "load_views", "parse_times", "rasterize", "rasterize_image",
           "rasterize_reference", "reconstruct", "render_sequence", "run", "run_poses", "save_ply", "train",
           "working_width"]
