"""The analysis written out: the results as export records (HDF5 and UFF), with the geometry's trace lines, and the
plots."""
from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from scipy.sparse.csgraph import minimum_spanning_tree
from scipy.spatial import cKDTree

from .correlation import mac
from .export import (
    CoherenceRecord,
    FRFRecord,
    Geometry,
    MACRecord,
    ShapeRecord,
    StabilisationRecord,
)
from .plots import write_plots
from .results_h5 import write_results_h5
from .uff import write_uff

if TYPE_CHECKING:
    from .result import AnalysisResult

log = logging.getLogger(__name__)

FORCE_NODE = 100            # the hammer's node id in the exported geometry, at the impact point
NO_NODE = 0                 # an FRF's reference node when the capture does not record the impact point
SENSOR_NODE0 = 1            # sensors are nodes 1..S, in channel order
SURFACE_NODE0 = 1001        # the video's surface points are 1001.., at most MAX_SURFACE_NODES of them
MAX_SURFACE_NODES = 2000
ACCEL_SET, VIDEO_SET = "accelerometers", "video"   # shape sets: UFF 55 load cases 1 and 2


def surface_subset(n_points: int, max_points: int = MAX_SURFACE_NODES) -> np.ndarray:
    """Indices of the surface points to export: all, or an even subsample (UFF files grow fast)."""
    if n_points <= max_points:
        return np.arange(n_points)
    return np.linspace(0, n_points - 1, max_points).round().astype(int)


def sensor_lines(node_ids: np.ndarray, coords_m: np.ndarray) -> list[tuple[int, int]]:
    """Trace lines joining the sensors: the minimum spanning tree over their positions (the shortest set of lines
    that joins them all). Sensors at one point (a triaxial mount's channels) are one point of the tree, joined
    through the first of them; they get no line between themselves."""
    node_ids, coords_m = np.asarray(node_ids), np.asarray(coords_m, float)
    if len(node_ids) < 2:
        return []
    _, first = np.unique(np.round(coords_m, 9), axis=0, return_index=True)
    first = np.sort(first)          # one node per distinct point, in channel order
    pts = coords_m[first]
    d = np.linalg.norm(pts[:, None] - pts[None], axis=2)
    tree = minimum_spanning_tree(np.triu(d)).tocoo()
    return sorted((int(node_ids[first[min(i, j)]]), int(node_ids[first[max(i, j)]]))
                  for i, j in zip(tree.row, tree.col))


def surface_lines(node_ids: np.ndarray, coords_m: np.ndarray, *, k: int = 8,
                  max_stretch: float = 2.5) -> list[tuple[int, int]]:
    """A wireframe over the surface points, as a mesh: the Gabriel graph of each point's k nearest neighbours (a
    line p-q is kept when no other point lies inside the sphere on p-q as diameter, which leaves about two lines
    per point, mostly the sides of near-regular triangles and quads, and no long diagonals), less lines longer
    than max_stretch times the larger of their two ends' nearest-neighbour distances (lines across gaps
    between parts). ME'scope draws every line, so sparse beats complete."""
    node_ids, p = np.asarray(node_ids), np.asarray(coords_m, float)
    n = len(p)
    if n < 2:
        return []
    tree = cKDTree(p)
    dist, nn = tree.query(p, k=min(k, n - 1) + 1)
    i = np.repeat(np.arange(n), nn.shape[1] - 1)
    j = nn[:, 1:].ravel()
    a, b = np.minimum(i, j), np.maximum(i, j)
    ab = np.unique(np.stack([a, b], axis=1), axis=0)
    a, b = ab[:, 0], ab[:, 1]
    length = np.linalg.norm(p[a] - p[b], axis=1)
    ok = length > 0
    spacing = np.maximum(dist[a, 1], dist[b, 1])
    ok &= length <= max_stretch * spacing
    mid = 0.5 * (p[a] + p[b])
    d_mid, _ = tree.query(mid, k=1)
    ok &= d_mid >= 0.5 * length * (1 - 1e-9)        # the nearest point to the midpoint is an end (or on the sphere)
    return [(int(node_ids[x]), int(node_ids[y])) for x, y in zip(a[ok], b[ok])]


def _mac_record(result: AnalysisResult, s_ids: np.ndarray) -> list[MACRecord]:
    out = []
    m = result.modes
    placed = np.array([s.placed for s in result.sensors], bool)
    if placed.sum() >= 2 and m.n_modes:
        shapes = m.shapes[:, placed]
        n = np.arange(1, m.n_modes + 1)
        out.append(MACRecord("accelerometer AutoMAC", mac(shapes, shapes), n, n, np.zeros((0, 2), int), np.zeros(0),
                             np.zeros(0, complex), np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0, int),
                             ACCEL_SET, ACCEL_SET))
    c, v = result.correlation, result.video
    if c is not None and v is not None:
        modes = np.asarray(v.mode_index, int) + 1          # rows and columns: the accelerometer mode numbers
        k = len(c.pairs)
        nan = np.full(k, np.nan)
        fa = nan if c.freq_a_hz is None else np.asarray(c.freq_a_hz, float)
        fb = nan if c.freq_b_hz is None else np.asarray(c.freq_b_hz, float)
        out.append(MACRecord("video vs accelerometers", c.mac, modes, modes, np.asarray(c.pairs, int).reshape(-1, 2),
                             c.pair_mac, c.scale_factor, fa, fb, c.comac, s_ids[:len(c.comac)], ACCEL_SET, VIDEO_SET))
    return out


def records(result: AnalysisResult) -> dict:
    """Geometry (sensors, the hammer, the video's surface points, trace lines), FRFs and their coherence, shapes
    (accelerometer modes and ODS; the video's modes, numbered as the accelerometer mode whose pole they were fitted
    with, and ODS), the MAC records and the stabilisation chart, as export records."""
    sensors = result.sensors
    s_ids = np.arange(SENSOR_NODE0, SENSOR_NODE0 + len(sensors))
    placed = np.array([s.placed for s in sensors], bool)
    frf = result.frf
    # A sensor without a position is a node of the FRFs (direction "scalar") but not of the geometry or shapes.
    coords = [np.stack([s.position_m for s in sensors if s.placed]) if placed.any() else np.zeros((0, 3))]
    ids = [s_ids[placed]]
    names = [s.name for s in sensors if s.placed]
    lines = sensor_lines(s_ids[placed], coords[0])
    ref = result.reference
    ref_node = NO_NODE
    if ref is not None and ref.position_m is not None:
        ref_node = FORCE_NODE
        ids.append(np.array([FORCE_NODE]))
        coords.append(np.asarray(ref.position_m, float)[None])
        names.append(f"hammer ({frf.input_name})")
    else:
        log.info("the capture does not record the impact point: no node %d; the FRFs' reference node is %d",
                 FORCE_NODE, NO_NODE)
    ref_dir = tuple(float(c) for c in ref.direction) if ref is not None and ref.direction is not None else "scalar"
    v = result.video
    sub = surface_subset(len(v.surface_points_m)) if v is not None else np.zeros(0, int)
    sid = SURFACE_NODE0 + np.arange(len(sub))
    if v is not None:
        ids.append(sid)
        coords.append(v.surface_points_m[sub])
        names += [f"gaussian {i}" for i in sub]
        lines += surface_lines(sid, v.surface_points_m[sub])
    node_ids = np.concatenate(ids)
    geometry = Geometry(node_ids, np.concatenate(coords), lines, names) if len(node_ids) else None
    dirs_all = [tuple(sn.direction) if sn.placed else "scalar" for sn in sensors]
    frfs = [FRFRecord(f"H1 {sn.name} by {frf.input_name}", int(i), d, ref_node, ref_dir, "accelerance",
                      frf.freq_hz, frf.h1[:, j])
            for j, (i, sn, d) in enumerate(zip(s_ids, sensors, dirs_all))]
    coh = np.asarray(frf.coherence, float).reshape(len(frf.freq_hz), -1)
    if not np.all(np.isfinite(coh)):   # lines where a spectrum is 0 (the force did not excite them): no coherence
        log.info("coherence: %d lines undefined (a spectrum is 0 there), written as 0", int(np.sum(~np.isfinite(coh))))
        coh = np.where(np.isfinite(coh), coh, 0.0)
    coherence = [CoherenceRecord(f"COH {sn.name} by {frf.input_name}", int(i), d, ref_node, ref_dir, frf.freq_hz,
                                 coh[:, j])
                 for j, (i, sn, d) in enumerate(zip(s_ids, sensors, dirs_all))]
    m = result.modes
    shapes = []
    if placed.any():
        dirs = np.stack([s.direction for s in sensors if s.placed])
        shapes += [ShapeRecord(f"accelerometer mode {k + 1}", float(m.freq_hz[k]), float(m.damping[k]),
                               s_ids[placed], m.shapes[k][placed][:, None] * dirs, "mode", "m/N", k + 1, ACCEL_SET)
                   for k in range(len(m.freq_hz))]
        for li, f in enumerate(result.ods_freq_hz):
            shapes.append(ShapeRecord(f"accelerometer ODS {f:.2f} Hz", float(f), 0.0, s_ids[placed],
                                      result.ods_accel[li][placed][:, None] * dirs, "ods", "m/N", li + 1, ACCEL_SET))
    if v is not None:
        for r, k in enumerate(v.mode_index):
            shapes.append(ShapeRecord(f"video mode {k + 1}", float(m.freq_hz[k]), float(m.damping[k]), sid,
                                      v.surface_residues[r][sub], "mode", "m/N", int(k) + 1, VIDEO_SET))
        for li, f in enumerate(result.ods_freq_hz[:len(result.ods_surface)]):
            shapes.append(ShapeRecord(f"video ODS {f:.2f} Hz", float(f), 0.0, sid, result.ods_surface[li][sub], "ods",
                                      "m/N", li + 1, VIDEO_SET))
    chart = m.chart
    order, poles, status = chart.flat()
    stab = [StabilisationRecord("accelerometers", order, poles, status, m.lsfd.poles_rad_s, chart.freq_tol,
                                chart.damping_tol, float(frf.exp_tau_s or 0.0))]
    return {"geometry": geometry, "frfs": frfs, "coherence": coherence, "shapes": shapes,
            "mac": _mac_record(result, s_ids), "stabilisation": stab}


def write_outputs(dest: Path, result: AnalysisResult, *, plots: bool = True,
                  capture_id: str | None = None) -> dict[str, str]:
    """results.h5 (recording `capture_id`, the capture's), analysis.uff and (with `plots`) the figures into dest;
    returns {what: file name}."""
    recs = records(result)
    write_results_h5(dest / "results.h5", **recs, attrs={"capture_takes": list(result.takes)},
                     capture_id=capture_id)
    write_uff(dest / "analysis.uff", geometry=recs["geometry"], frfs=recs["frfs"], coherence=recs["coherence"],
              shapes=recs["shapes"], description="odsplat analysis")
    files = {"results": "results.h5", "uff": "analysis.uff"}
    if plots:
        files.update(write_plots(dest, result))
    return files
