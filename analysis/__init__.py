"""Analysis: FRFs and modal parameters from hammer and accelerometers, quantitative 3D ODS from the dynamic
Gaussians, 2D tracking as a cross-check, correlation (MAC, CoMAC), exports (UFF, HDF5), plots and a report.

Public surface: two stage entries, `run(capture, AnalyzeSettings) -> AnalysisResult` (alias `analyze_capture`;
saved to derived/analysis/) and `write_report(capture)` (derived/analysis/report.html), and the pieces they are
made of for use on their own."""
from .analyze import AnalyzeSettings, analyze_capture, structure_mask
from .correlation import Correlation, comac, correlate, mac, modal_scale_factor
from .document import AnalysisDocument, read_analysis
from .ema import LSFDResult, ModalFit, StabilisationChart, fit_modes, lscf, lsfd, select_poles, stabilisation
from .export import (
    CoherenceRecord,
    FRFRecord,
    Geometry,
    MACRecord,
    ResultSet,
    ShapeRecord,
    StabilisationRecord,
    TimeSeries,
)
from .frf import FRFResult, FRFSettings, HitCheck, check_frf_hit, estimate_frf, split_hits
from .ods import (
    DecayFit,
    SurfaceMotion,
    fit_decay,
    force_transform,
    lsce_poles,
    pencil_poles,
    receptance,
    stable_poles,
)
from .report import write_report
from .result import AnalysisResult, Sensor, VideoModes
from .results_h5 import read_results_h5, write_results_h5
from .shape3d import surface_mesh
from .tracking import Tracks, good_points, project_displacement, track_points
from .uff import read_uff, write_uff
from .video2d import has_video2d, read_video2d

run = analyze_capture  # the analyze stage's entry

__all__ = ["AnalysisDocument", "AnalysisResult", "AnalyzeSettings", "CoherenceRecord", "Correlation", "DecayFit",
           "FRFRecord", "FRFResult", "FRFSettings", "Geometry", "HitCheck", "LSFDResult", "MACRecord", "ModalFit",
           "ResultSet", "Sensor", "ShapeRecord", "StabilisationChart", "StabilisationRecord", "SurfaceMotion",
           "TimeSeries", "Tracks", "VideoModes", "analyze_capture", "check_frf_hit", "comac", "correlate",
           "estimate_frf", "fit_decay", "fit_modes", "force_transform", "good_points", "has_video2d", "lsce_poles",
           "lscf", "lsfd", "mac", "modal_scale_factor", "pencil_poles", "project_displacement", "read_analysis",
           "read_results_h5", "read_uff", "read_video2d", "receptance", "run", "select_poles", "split_hits",
           "stabilisation", "stable_poles", "structure_mask", "surface_mesh", "track_points", "write_report",
           "write_results_h5", "write_uff"]
