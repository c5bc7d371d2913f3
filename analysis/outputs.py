"""The analysis written out: the results as export records (HDF5 and UFF), and the plots."""
from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .export import FRFRecord, Geometry, ShapeRecord, write_results_h5, write_uff
from .plots import write_plots

if TYPE_CHECKING:
    from .result import AnalysisResult

log = logging.getLogger(__name__)

FORCE_NODE = 100            # the hammer's node id in the exported geometry
SENSOR_NODE0 = 1            # sensors are nodes 1..S, in channel order
SURFACE_NODE0 = 1001        # the video's surface points are 1001.., at most MAX_SURFACE_NODES of them
MAX_SURFACE_NODES = 2000


def surface_subset(n_points: int, max_points: int = MAX_SURFACE_NODES) -> np.ndarray:
    """Indices of the surface points to export: all, or an even subsample (UFF files grow fast)."""
    if n_points <= max_points:
        return np.arange(n_points)
    return np.linspace(0, n_points - 1, max_points).round().astype(int)


def records(result: AnalysisResult) -> dict:
    """Geometry, FRFs and shapes (accelerometer modes, video modes, both ODS) as export records."""
    sensors = result.sensors
    s_ids = np.arange(SENSOR_NODE0, SENSOR_NODE0 + len(sensors))
    placed = np.array([s.placed for s in sensors], bool)
    # A sensor without a position is a node of the FRFs (direction "scalar") but not of the geometry or shapes.
    coords = [np.stack([s.position_m for s in sensors if s.placed]) if placed.any() else np.zeros((0, 3))]
    ids = [s_ids[placed]]
    names = [s.name for s in sensors if s.placed]
    v = result.video
    sub = surface_subset(len(v.surface_points_m)) if v is not None else np.zeros(0, int)
    if v is not None:
        ids.append(SURFACE_NODE0 + np.arange(len(sub)))
        coords.append(v.surface_points_m[sub])
        names += [f"gaussian {i}" for i in sub]
    node_ids = np.concatenate(ids)
    geometry = Geometry(node_ids, np.concatenate(coords), None, names) if len(node_ids) else None
    frf = result.frf
    frfs = [FRFRecord(f"H1 {sn.name} by {frf.input_name}", int(i),
                      tuple(sn.direction) if sn.placed else "scalar", FORCE_NODE, "scalar",
                      "accelerance", frf.freq_hz, frf.h1[:, j])
            for j, (i, sn) in enumerate(zip(s_ids, sensors))]
    m = result.modes
    shapes = []
    if placed.any():
        dirs = np.stack([s.direction for s in sensors if s.placed])
        shapes += [ShapeRecord(f"accelerometer mode {k + 1}", float(m.freq_hz[k]), float(m.damping[k]),
                               s_ids[placed], m.shapes[k][placed][:, None] * dirs, "mode", "m/N")
                   for k in range(len(m.freq_hz))]
        for li, f in enumerate(result.ods_freq_hz):
            shapes.append(ShapeRecord(f"accelerometer ODS {f:.2f} Hz", float(f), 0.0, s_ids[placed],
                                      result.ods_accel[li][placed][:, None] * dirs, "ods", "m/N"))
    if v is not None:
        sid = SURFACE_NODE0 + np.arange(len(sub))
        for r, k in enumerate(v.mode_index):
            shapes.append(ShapeRecord(f"video mode {k + 1}", float(m.freq_hz[k]), float(m.damping[k]), sid,
                                      v.surface_residues[r][sub], "mode", "m/N"))
        for li, f in enumerate(result.ods_freq_hz[:len(result.ods_surface)]):
            shapes.append(ShapeRecord(f"video ODS {f:.2f} Hz", float(f), 0.0, sid, result.ods_surface[li][sub], "ods",
                                      "m/N"))
    return {"geometry": geometry, "frfs": frfs, "shapes": shapes}


def write_outputs(dest: Path, result: AnalysisResult) -> dict[str, str]:
    """results.h5, analysis.uff and the plots into dest; returns {what: file name}."""
    recs = records(result)
    write_results_h5(dest / "results.h5", **recs, attrs={"capture_takes": list(result.takes)})
    write_uff(dest / "analysis.uff", **recs, description="odsplat analysis")
    files = {"results": "results.h5", "uff": "analysis.uff"}
    files.update(write_plots(dest, result))
    return files
