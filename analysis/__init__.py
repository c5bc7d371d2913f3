"""Analysis: FRFs and modal parameters from hammer and accelerometers, quantitative 3D ODS from the dynamic
Gaussians, 2D tracking as a cross-check, correlation (MAC, CoMAC), exports (UFF, HDF5), plots and a report.

Public surface: `analyze_capture(capture, AnalyzeSettings) -> AnalysisResult` (also derived/analysis/), and the
pieces it is made of for use on their own."""
from .correlation import Correlation, comac, correlate, mac, modal_scale_factor
from .ema import LSFDResult, ModalFit, StabilisationChart, fit_modes, lscf, lsfd, select_poles, stabilisation
from .export import (
           FRFRecord,
           Geometry,
           ResultSet,
           ShapeRecord,
           TimeSeries,
           read_results_h5,
           read_uff,
           write_results_h5,
           write_uff,
)
from .frf import FRFResult, FRFSettings, HitCheck, check_hit, estimate_frf, split_hits
from .ods import DecayFit, SurfaceMotion, fit_decay, force_transform, lsce_poles, pencil_poles, receptance, stable_poles
from .run import AnalysisResult, AnalyzeSettings, Sensor, VideoModes, analyze_capture
from .tracking import Tracks, good_points, project_displacement, track_points

__all__ = ["AnalysisResult", "AnalyzeSettings", "Correlation", "DecayFit", "FRFRecord", "FRFResult", "FRFSettings",
           "Geometry", "HitCheck", "LSFDResult", "ModalFit", "ResultSet", "Sensor", "ShapeRecord",
           "StabilisationChart", "SurfaceMotion", "TimeSeries", "Tracks", "VideoModes", "analyze_capture",
           "check_hit", "comac", "correlate", "estimate_frf", "fit_decay", "fit_modes", "force_transform",
           "good_points", "lscf", "lsce_poles", "lsfd", "mac", "modal_scale_factor", "pencil_poles",
           "project_displacement", "read_results_h5", "read_uff", "receptance", "select_poles", "split_hits",
           "stabilisation", "stable_poles", "track_points", "write_results_h5", "write_uff"]
