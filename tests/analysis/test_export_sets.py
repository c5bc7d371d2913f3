"""The exports an engineer reads in a modal tool: coherence beside the FRFs (UFF 58, function type 6), shapes of
two instruments numbered by the same modes (UFF 55 load cases), MAC and stabilisation records in results.h5, and
the trace lines (UFF 82) the analysis draws between sensors and over the video's surface points."""
from __future__ import annotations

import h5py
import numpy as np
import pytest
import pyuff

from odsplat.analysis.ema import lscf, stabilisation
from odsplat.analysis.export import (
    CoherenceRecord,
    FRFRecord,
    Geometry,
    MACRecord,
    ShapeRecord,
    StabilisationRecord,
    TimeSeries,
)
from odsplat.analysis.outputs import sensor_lines, surface_lines
from odsplat.analysis.results_h5 import read_results_h5, write_results_h5
from odsplat.analysis.uff import read_uff, write_uff
from odsplat.spine.errors import InputError

FREQ_HZ = 0.5 * np.arange(401)
MODES_HZ = ((12.5, 0.02), (31.0, 0.01), (77.0, 0.015))
SENSORS = np.array([1, 2, 3, 4])
SURFACE = np.array([1001, 1002, 1003, 1004, 1005])


def _accelerance(fn_hz: float, zeta: float) -> np.ndarray:
    w, wn = 2 * np.pi * FREQ_HZ, 2 * np.pi * fn_hz
    return -w ** 2 / (wn ** 2 - w ** 2 + 2j * zeta * wn * w)


@pytest.fixture
def rec():
    """Four sensors, the hammer (node 100) and five surface points; FRFs and coherence per sensor; three modes and
    one ODS from the accelerometers and the same three modes (same poles) and ODS from the video."""
    rng = np.random.default_rng(11)
    ids = np.concatenate([SENSORS, [100], SURFACE])
    geometry = Geometry(ids, rng.uniform(-0.5, 0.5, (len(ids), 3)), [(1, 2), (2, 3), (3, 4), (1001, 1002)])
    frfs, coherence = [], []
    for node in SENSORS:
        h = sum(rng.uniform(0.5, 2) * _accelerance(f, z) for f, z in MODES_HZ)
        frfs.append(FRFRecord(f"H1 acc{node} by force", node, "+Z", 100, (0.0, -0.6, -0.8), "accelerance", FREQ_HZ, h))
        coherence.append(CoherenceRecord(f"COH acc{node} by force", node, "+Z", 100, (0.0, -0.6, -0.8), FREQ_HZ,
                                         rng.uniform(0.2, 1.0, len(FREQ_HZ))))
    shapes = []
    for set_name, nodes in (("accelerometers", SENSORS), ("video", SURFACE)):
        prefix = set_name.rstrip("s")
        shapes += [ShapeRecord(f"{prefix} mode {k + 1}", f, z, nodes,
                               rng.normal(size=(len(nodes), 3)) + 1j * rng.normal(size=(len(nodes), 3)),
                               unit="m/N", number=k + 1, shape_set=set_name) for k, (f, z) in enumerate(MODES_HZ)]
        shapes.append(ShapeRecord(f"{prefix} ODS 40.00 Hz", 40.0, 0.0, nodes, rng.normal(size=(len(nodes), 3)) * 1e-6,
                                  kind="ods", unit="m/N", number=1, shape_set=set_name))
    return dict(geometry=geometry, frfs=frfs, coherence=coherence, shapes=shapes)


# ------------------------------------------------------------------------------------------------- UFF, pyuff

def test_pyuff_reads_every_dataset_we_write(tmp_path, rec):
    """Each dataset type we write (151, 164, 2411, 82, 58 time / FRF / coherence, 55 mode / ODS) as pyuff reads it,
    and our reader's round trip of the new fields."""
    t = np.arange(200) / 1000.0
    ts = TimeSeries("force", 100, (0.0, -0.6, -0.8), "force", "N", 0.0, 1e-3, np.exp(-((t - 0.01) / 1e-3) ** 2))
    path = write_uff(tmp_path / "a.uff", time_series=[ts], description="two sets", **rec)
    sets = pyuff.UFF(str(path)).read_sets()
    types = [s["type"] for s in sets]
    assert types == [151, 164, 2411, 82] + [58] * 9 + [55] * 8
    assert sorted(set(types)) == [55, 58, 82, 151, 164, 2411]
    np.testing.assert_array_equal(sets[2]["node_nums"], rec["geometry"].node_ids)
    f58 = sets[4:13]
    assert [s["func_type"] for s in f58] == [1] + [4] * 4 + [6] * 4
    for s, c in zip(f58[5:], rec["coherence"]):
        assert (s["rsp_node"], s["rsp_dir"], s["ref_node"], s["ref_dir"]) == (c.response_node, 3, 100, -3)
        assert s["ord_data_type"] == 4 and not np.iscomplexobj(s["data"])           # real, double precision
        assert s["abscissa_min"] == 0.0 and s["abscissa_inc"] == 0.5 and s["num_pts"] == len(FREQ_HZ)
        np.testing.assert_allclose(s["data"], c.values, rtol=1e-11, atol=1e-12)
        assert s["id5"] == "ref=(0.000000,-0.600000,-0.800000)"
    # 55: mode k of each set is mode_n k; the set is the load case and the ID lines say which it is
    f55 = sets[13:]
    assert [(s["load_case"], s["analysis_type"]) for s in f55] == [(1, 3)] * 3 + [(1, 5)] + [(2, 3)] * 3 + [(2, 5)]
    assert [s.get("mode_n", s.get("freq_step_n")) for s in f55] == [1, 2, 3, 1] * 2
    for s, (f, z) in zip(f55[:3] + f55[4:7], MODES_HZ * 2):
        assert abs(s["eig"]) / (2 * np.pi) == pytest.approx(f, rel=1e-5)
        assert -s["eig"].real / abs(s["eig"]) == pytest.approx(z, rel=1e-4)
    assert f55[4]["id1"].strip() == "video mode 1" and "set=video" in f55[4]["id4"]
    assert "set=accelerometers" in f55[0]["id4"] and "unit=m/N" in f55[0]["id4"]

    back = read_uff(path)
    assert back.skipped == [] and [c.name for c in back.coherence] == [c.name for c in rec["coherence"]]
    for got, want in zip(back.coherence, rec["coherence"]):
        assert (got.response_node, got.reference_node, got.response_direction) == (want.response_node, 100, "+Z")
        np.testing.assert_allclose(got.reference_direction, want.reference_direction, atol=1e-6)
        np.testing.assert_allclose(got.values, want.values, rtol=1e-11, atol=1e-12)
    assert [(s.shape_set, s.kind, s.number) for s in back.shapes] == [(s.shape_set, s.kind, s.number)
                                                                       for s in rec["shapes"]]


def test_shapes_are_numbered_within_their_set(tmp_path, rec):
    """Unnumbered shapes count 1.. within their set and kind; two of one set may not share a number."""
    plain = [ShapeRecord(s.name, s.freq_hz, s.damping, s.node_ids, s.values, s.kind, s.unit, shape_set=s.shape_set)
             for s in rec["shapes"]]
    sets = pyuff.UFF(str(write_uff(tmp_path / "b.uff", geometry=rec["geometry"], shapes=plain))).read_sets()
    f55 = [s for s in sets if s["type"] == 55]
    assert [(s["load_case"], s.get("mode_n", s.get("freq_step_n"))) for s in f55] == [
        (1, 1), (1, 2), (1, 3), (1, 1), (2, 1), (2, 2), (2, 3), (2, 1)]
    clash = ShapeRecord("video mode 2 again", 31.0, 0.01, SURFACE, np.ones((5, 3)), number=2, shape_set="video")
    for write, name in ((write_uff, "bad.uff"), (write_results_h5, "bad.h5")):
        with pytest.raises(InputError, match=r"'video mode 2 again'.*mode number 2 of set 'video' is also "
                                             r"'video mode 2'"):
            write(tmp_path / name, geometry=rec["geometry"], shapes=[*rec["shapes"], clash])
        assert not (tmp_path / name).exists()
    with pytest.raises(InputError, match="shape_set"):
        ShapeRecord("m", 10.0, 0.01, [1], np.ones((1, 3)), shape_set="two words")
    with pytest.raises(InputError, match=r"coherence 'c'.*lies in \[0, 1\]"):
        CoherenceRecord("c", 1, "+Z", 100, "-Z", [0.0, 1.0], [0.5, 1.2])


# ------------------------------------------------------------------------------------------------------ HDF5

def _stabilisation() -> StabilisationRecord:
    """A real chart: LSCF on a two-output sum of the three modes, orders 2..24."""
    frf = np.stack([_accelerance(f, z) * g for (f, z), g in zip(MODES_HZ, (1.0, -0.7, 0.4))], axis=1).sum(axis=1)
    frf = np.stack([frf, 0.5 * frf + _accelerance(31.0, 0.01)], axis=1)
    chart = stabilisation(lscf(FREQ_HZ, frf, max_order=24, fmin_hz=2.0, fmax_hz=150.0))
    order, poles, status = chart.flat()
    selected = np.array([-z * 2 * np.pi * f + 2j * np.pi * f * np.sqrt(1 - z * z) for f, z in MODES_HZ])
    return StabilisationRecord("accelerometers", order, poles, status, selected, chart.freq_tol, chart.damping_tol,
                               0.25)


def test_h5_round_trip_of_coherence_mac_and_stabilisation(tmp_path, rec):
    rng = np.random.default_rng(3)
    m = rng.uniform(0, 1, (3, 3))
    mac = MACRecord("video vs accelerometers", m, [1, 2, 3], [1, 2, 3], [(0, 0), (1, 1), (2, 2)], np.diag(m),
                    rng.normal(size=3) + 1j * rng.normal(size=3), [12.5, 31.0, 77.0], [np.nan, 31.1, 76.8],
                    rng.uniform(0, 1, 4), SENSORS, "accelerometers", "video")
    stab = _stabilisation()
    assert {"stable", "new"} <= set(stab.status.tolist())
    path = write_results_h5(tmp_path / "results.h5", mac=[mac], stabilisation=[stab], **rec)
    with h5py.File(path, "r") as f:
        assert f.attrs["schema_version"] == 3
        assert list(f) == ["geometry", "frfs", "shapes", "coherence", "mac", "stabilisation"]
        assert f["coherence/COH acc1 by force/values"].dtype == np.float64
        assert f["stabilisation/accelerometers/status"].asstr()[0] == stab.status[0]
    back = read_results_h5(path)
    for kind, want in (("coherence", rec["coherence"]), ("mac", [mac]), ("stabilisation", [stab]),
                       ("shapes", rec["shapes"])):
        got = getattr(back, kind)
        assert [r.name for r in got] == [r.name for r in want]
        for g, w in zip(got, want):
            for key, value in vars(w).items():
                if isinstance(value, np.ndarray):
                    np.testing.assert_array_equal(getattr(g, key), value, err_msg=f"{kind}.{key}")
                    assert getattr(g, key).dtype.kind == value.dtype.kind, (kind, key)
                else:
                    assert getattr(g, key) == value, (kind, key)
    np.testing.assert_allclose(back.stabilisation[0].freq_hz, np.abs(stab.poles_rad_s) / (2 * np.pi))


def test_h5_of_schema_2_reads_with_defaults(tmp_path, rec):
    """A file written before shapes had a number and a set (schema 2) reads back, numbered by order, set ''."""
    path = write_results_h5(tmp_path / "old.h5", geometry=rec["geometry"], shapes=rec["shapes"][:2])
    with h5py.File(path, "r+") as f:
        f.attrs["schema_version"] = 2
        for g in f["shapes"].values():
            del g.attrs["number"], g.attrs["shape_set"]
    back = read_results_h5(path)
    assert [(s.name, s.number, s.shape_set) for s in back.shapes] == [("accelerometer mode 1", 0, ""),
                                                                      ("accelerometer mode 2", 0, "")]


# ------------------------------------------------------------------------------------------------ trace lines

def test_sensor_lines_are_the_shortest_tree():
    """Sensors along an arm in shuffled channel order are joined in their order along it; a triaxial mount (three
    channels at one point) joins the tree once, with no zero-length lines."""
    along = np.array([0.0, 0.3, 0.1, 0.5, 0.2])
    coords = np.stack([along, 0.01 * along, np.zeros(5)], axis=1)
    coords = np.concatenate([coords, np.repeat([[0.5, 0.2, 0.0]], 3, axis=0)])   # nodes 6-8: a triax
    ids = np.arange(1, 9)
    lines = sensor_lines(ids, coords)
    assert lines == [(1, 3), (2, 4), (2, 5), (3, 5), (4, 6)]
    assert sensor_lines(ids[:1], coords[:1]) == []


def _plates(rng, n: int = 400) -> np.ndarray:
    """Two 0.3 x 0.2 m plates 5 cm apart, each with n points at random (as a reconstruction's Gaussians are)."""
    a = np.stack([rng.uniform(0, 0.3, n), rng.uniform(0, 0.2, n), np.zeros(n)], axis=1)
    b = a.copy() + [0.0, 0.0, 0.05]
    b[:, :2] = np.stack([rng.uniform(0, 0.3, n), rng.uniform(0, 0.2, n)], axis=1)
    return np.concatenate([a, b])


def test_surface_wireframe_is_a_readable_mesh():
    rng = np.random.default_rng(5)
    pts = _plates(rng)
    ids = 1001 + np.arange(len(pts))
    lines = surface_lines(ids, pts)
    a, b = (np.array(x) - 1001 for x in zip(*lines))
    assert len(set(lines)) == len(lines) and all(p < q for p, q in lines)
    assert set(np.concatenate([a, b]).tolist()) <= set(range(len(pts)))          # only existing nodes
    assert Geometry(ids, pts, lines).lines == lines                                 # and the writer agrees
    # readable: about two lines per point (a complete k-nearest graph would be about 5)
    assert 1.5 < len(lines) / len(pts) < 2.5, len(lines) / len(pts)
    # no line from one plate to the other, 5 cm apart where points are about 1 cm apart
    assert np.all(np.abs(pts[a, 2] - pts[b, 2]) < 1e-12)
    # each plate's mesh holds together: one connected piece per plate (but a stray point or two)
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    n, labels = connected_components(coo_matrix((np.ones(len(a)), (a, b)), shape=(len(pts),) * 2), directed=False)
    sizes = np.sort(np.bincount(labels))[::-1]
    assert sizes[0] >= 390 and sizes[1] >= 390 and sizes[:2].sum() >= len(pts) - 6, sizes[:4]
    # mesh-like: no line crosses a shorter one in the plane (a Gabriel graph is planar)
    p2 = pts[:400, :2]
    on_a = pts[a, 2] == 0
    seg = np.stack([p2[a[on_a]], p2[b[on_a]]], axis=1)
    crossings = 0
    for i in range(0, len(seg), 7):                                             # a sample of lines
        p, r = seg[i, 0], seg[i, 1] - seg[i, 0]
        q, s = seg[:, 0], seg[:, 1] - seg[:, 0]
        den = r[0] * s[:, 1] - r[1] * s[:, 0]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((q - p)[:, 0] * s[:, 1] - (q - p)[:, 1] * s[:, 0]) / den
            u = ((q - p)[:, 0] * r[1] - (q - p)[:, 1] * r[0]) / den
        crossings += int(np.sum((t > 1e-9) & (t < 1 - 1e-9) & (u > 1e-9) & (u < 1 - 1e-9)))
    assert crossings == 0
