"""Export to universal files (checked through pyuff itself and against files written by commercial tools) and to
the HDF5 results layout, and back."""
from __future__ import annotations

import h5py
import numpy as np
import pytest
import pyuff

from odsplat.analysis.export import (
    FRFRecord,
    Geometry,
    ShapeRecord,
    TimeSeries,
)
from odsplat.analysis.results_h5 import read_results_h5, write_results_h5
from odsplat.analysis.uff import read_uff, write_uff
from odsplat.spine.errors import InputError, OdsplatError

DT_S = 1 / 51200          # not representable in the 6 digits of a UFF 58 header: exercises its rounding
T0_S = -0.002
DF_HZ = 0.25
NODES = np.array([101, 102, 103, 104, 105, 106])
LINES = [(101, 102), (102, 103), (103, 104), (104, 105), (105, 106)]
POLES_HZ = ((12.5, 0.02), (31.0, 0.01))


def _sdof(freq_hz: np.ndarray, fn_hz: float, zeta: float, power: int) -> np.ndarray:
    """(i w)^power times the receptance of a unit-mass oscillator: power 0, 1, 2 for receptance, mobility,
    accelerance."""
    w, wn = 2 * np.pi * freq_hz, 2 * np.pi * fn_hz
    return (1j * w) ** power / (wn ** 2 - w ** 2 + 2j * zeta * wn * w)


@pytest.fixture
def rec():
    """Geometry (6 nodes, 5 lines), 2 time series, 3 FRFs, 2 modes and 1 ODS."""
    rng = np.random.default_rng(7)
    t = T0_S + DT_S * np.arange(400)
    geometry = Geometry(NODES, rng.uniform(-0.5, 0.5, (6, 3)), LINES, names=[f"p{n}" for n in NODES])
    hammer = np.where(np.abs(t) < 2e-4, 120.0 * np.cos(np.pi * t / 4e-4) ** 2, 0.0)
    accel = 3.5 * np.exp(-2.0 * t) * np.sin(2 * np.pi * 31.0 * t) * (t > 0)
    time_series = [TimeSeries("hammer", 101, "-Z", "force", "N", T0_S, DT_S, hammer),
                   TimeSeries("acc 103", 103, (0.6, 0.8, 0.0), "acceleration", "m/s^2", T0_S, DT_S, accel)]
    freq = DF_HZ * np.arange(801)
    frfs = [FRFRecord(f"H{node}", node, "+Z", 101, "-Z", quantity, freq, 0.3 * _sdof(freq, 31.0, 0.01, power))
            for node, quantity, power in ((102, "accelerance", 2), (103, "mobility", 1), (104, "receptance", 0))]
    modes = [ShapeRecord("mode 1", 12.5, 0.02, NODES, rng.normal(size=(6, 3)) + 1j * rng.normal(size=(6, 3))),
             ShapeRecord("mode 2", 31.0, 0.01, NODES[::-1], rng.normal(size=(6, 3)))]
    ods_m_per_n = 1e-6 * (rng.normal(size=(4, 3)) + 1j * rng.normal(size=(4, 3)))
    ods = ShapeRecord("ODS 40 Hz", 40.0, 0.0, NODES[:4], ods_m_per_n, kind="ods", unit="m/N")
    return dict(geometry=geometry, time_series=time_series, frfs=frfs, shapes=[*modes, ods])


def _segments(nodes) -> list[tuple[int, int]]:
    seq = [int(n) for n in nodes]
    return [(a, b) for a, b in zip(seq[:-1], seq[1:]) if a and b]


# --------------------------------------------------------------------------------------------------- UFF, pyuff

def test_uff_datasets_as_pyuff_reads_them(tmp_path, rec):
    path = write_uff(tmp_path / "test.uff", description="plate impact test", **rec)
    sets = pyuff.UFF(str(path)).read_sets()
    assert [s["type"] for s in sets] == [151, 164, 2411, 82, 58, 58, 58, 58, 58, 55, 55, 55]
    header, units, nodes, lines = sets[:4]
    assert header["model_name"] == "plate impact test" and "SI" in header["description"]
    assert (units["units_code"], units["length"], units["force"]) == (1, 1.0, 1.0)
    np.testing.assert_array_equal(nodes["node_nums"], NODES)
    coords = np.stack([nodes["x"], nodes["y"], nodes["z"]], axis=1)
    np.testing.assert_allclose(coords, rec["geometry"].coords_m, rtol=1e-15, atol=1e-16)
    assert _segments(lines["nodes"]) == LINES

    hammer, accel = sets[4:6]
    assert (hammer["func_type"], hammer["rsp_node"], hammer["rsp_dir"], hammer["ref_node"]) == (1, 101, -3, 0)
    assert (hammer["ord_data_type"], hammer["abscissa_spacing"], hammer["num_pts"]) == (4, 1, 400)
    assert (hammer["abscissa_spec_data_type"], hammer["ordinate_spec_data_type"]) == (17, 13)
    assert (hammer["abscissa_axis_units_lab"], hammer["ordinate_axis_units_lab"]) == ("s", "N")
    assert hammer["abscissa_inc"] == pytest.approx(DT_S, rel=1e-5) and hammer["abscissa_inc"] != DT_S
    assert hammer["abscissa_min"] == pytest.approx(T0_S, rel=1e-5)
    np.testing.assert_allclose(hammer["data"], rec["time_series"][0].values, rtol=1e-10, atol=1e-9)
    assert accel["rsp_dir"] == 2 and accel["id5"] == "rsp=(0.600000,0.800000,0.000000)"   # nearest axis: +Y
    assert accel["ordinate_spec_data_type"] == 12 and accel["id1"] == "acc 103"

    for s, frf, spec in zip(sets[6:9], rec["frfs"], (12, 11, 8)):
        assert (s["func_type"], s["ord_data_type"], s["load_case_id"]) == (4, 6, 0)
        assert (s["rsp_node"], s["rsp_dir"], s["ref_node"], s["ref_dir"]) == (frf.response_node, 3, 101, -3)
        specs = (s["abscissa_spec_data_type"], s["ordinate_spec_data_type"], s["orddenom_spec_data_type"])
        assert specs == (18, spec, 13)
        assert s["abscissa_inc"] == DF_HZ and s["abscissa_min"] == 0.0 and s["orddenom_axis_units_lab"] == "N"
        assert np.iscomplexobj(s["data"]) and len(s["data"]) == 801
        np.testing.assert_allclose(s["data"], frf.values, rtol=1e-10, atol=1e-10 * np.abs(frf.values).max())

    mode1, mode2, ods = sets[9:]
    assert [s["analysis_type"] for s in sets[9:]] == [3, 2, 5]                  # complex mode, real mode, ODS
    assert [s["data_type"] for s in sets[9:]] == [5, 2, 5]
    assert all(s["data_ch"] == 2 and s["n_data_per_node"] == 3 for s in sets[9:])
    eig = mode1["eig"]                                                          # rad/s: -zeta wn + i wd
    assert abs(eig) / (2 * np.pi) == pytest.approx(12.5, rel=1e-5)
    assert -eig.real / abs(eig) == pytest.approx(0.02, rel=1e-4)
    assert (mode1["mode_n"], mode2["mode_n"], mode2["freq"], mode2["modal_damp_vis"]) == (1, 2, 31.0, 0.01)
    assert (ods["freq"], ods["freq_step_n"], ods["spec_data_type"]) == (40.0, 1, 8)
    np.testing.assert_array_equal(mode2["node_nums"], NODES[::-1])
    for s, shape in zip(sets[9:], rec["shapes"]):
        got = np.stack([s["r1"], s["r2"], s["r3"]], axis=1)
        np.testing.assert_allclose(got, shape.values, rtol=1e-5, atol=1e-5 * np.abs(shape.values).max())


def test_uff_round_trip(tmp_path, rec):
    back = read_uff(write_uff(tmp_path / "test.uff", description="plate impact test", **rec))
    assert back.description == "plate impact test" and back.skipped == []
    np.testing.assert_array_equal(back.geometry.node_ids, NODES)
    np.testing.assert_allclose(back.geometry.coords_m, rec["geometry"].coords_m, rtol=1e-15, atol=1e-16)
    assert back.geometry.lines == LINES and back.geometry.names is None          # UFF has no node names
    assert [t.name for t in back.time_series] == ["hammer", "acc 103"]
    for got, want in zip(back.time_series, rec["time_series"]):
        assert (got.node_id, got.quantity, got.unit) == (want.node_id, want.quantity, want.unit)
        assert got.dt_s == pytest.approx(DT_S, rel=1e-5) and got.t0_s == pytest.approx(T0_S, rel=1e-5)
        np.testing.assert_allclose(got.values, want.values, rtol=1e-10, atol=1e-9)
    assert back.time_series[0].direction == "-Z"
    np.testing.assert_allclose(back.time_series[1].direction, (0.6, 0.8, 0.0), atol=1e-6)
    assert [(f.name, f.quantity, f.unit) for f in back.frfs] == [
        ("H102", "accelerance", "m/s^2/N"), ("H103", "mobility", "m/s/N"), ("H104", "receptance", "m/N")]
    for got, want in zip(back.frfs, rec["frfs"]):
        assert (got.response_node, got.response_direction, got.reference_node, got.reference_direction) == (
            want.response_node, "+Z", 101, "-Z")
        np.testing.assert_allclose(got.freq_hz, want.freq_hz, rtol=0, atol=1e-9)
        np.testing.assert_allclose(got.values, want.values, rtol=1e-10, atol=1e-10 * np.abs(want.values).max())
    assert [(s.name, s.kind, s.unit) for s in back.shapes] == [("mode 1", "mode", "m"), ("mode 2", "mode", "m"),
                                                                ("ODS 40 Hz", "ods", "m/N")]
    for got, want in zip(back.shapes, rec["shapes"]):
        assert got.freq_hz == pytest.approx(want.freq_hz, rel=1e-5)
        assert got.damping == pytest.approx(want.damping, rel=1e-4, abs=1e-12)
        np.testing.assert_array_equal(got.node_ids, want.node_ids)
        np.testing.assert_allclose(got.values, want.values, rtol=1e-5, atol=1e-5 * np.abs(want.values).max())


# ------------------------------------------------------------------------------------------- UFF by other tools

def test_reads_a_simcenter_time_record(shared_data):
    """A microphone time record from Simcenter Testlab: dataset 58, function type 1, 79292 samples."""
    back = read_uff(shared_data / "pyuff-samples" / "Sample_UFF58_ascii.uff")
    assert back.geometry is None and back.frfs == [] and back.shapes == [] and len(back.time_series) == 1
    ts = back.time_series[0]
    assert (ts.name, ts.node_id, ts.direction, ts.quantity, ts.unit) == ("Mic 01.0Scalar", 0, "+X", "pressure", "Pa")
    assert len(ts.values) == 79292 and ts.t0_s == 0.0 and ts.dt_s == pytest.approx(1.52588e-05, rel=1e-9)
    assert ts.values[0] == pytest.approx(-1.47553e-02) and ts.values[1] == pytest.approx(-1.72957e-02)
    assert ts.values[-1] == pytest.approx(-4.31469e-03)
    binary = read_uff(shared_data / "pyuff-samples" / "Sample_UFF58b_bin.uff").time_series[0]  # the same, 58b
    np.testing.assert_allclose(binary.values, ts.values, rtol=0, atol=1e-6)


def test_reads_normal_mode_records(shared_data):
    back = read_uff(shared_data / "pyuff-samples" / "uff55_translation.uff")
    assert back.time_series == [] and back.frfs == [] and len(back.shapes) == 3
    assert [(s.name, s.kind, s.freq_hz, s.damping, s.unit) for s in back.shapes] == [
        ("mode 1", "mode", 10.0, 0.0, "m"), ("mode 2", "mode", 12.0, 0.0, "m"), ("mode 3", "mode", 13.0, 0.0, "m")]
    np.testing.assert_array_equal(back.shapes[0].node_ids, [1, 2, 3, 4])
    np.testing.assert_allclose(back.shapes[0].values[0], [-1.46518] * 3)
    np.testing.assert_allclose(back.shapes[1].values[3], [1.98289] * 3)
    np.testing.assert_allclose(back.shapes[2].values[:, 2], [-0.63467, -0.662803, 1.48845, -0.795555])


def test_reads_testlab_geometry(shared_data):
    """Nodes as dataset 15 and trace lines (dataset 82) from LMS Test.Lab; dataset 18 is listed as skipped."""
    back = read_uff(shared_data / "pyuff-samples" / "TestLab 161 164 18 15 82.uff")
    g = back.geometry
    assert len(g.node_ids) == 36 and g.node_ids[0] == 1
    np.testing.assert_allclose(g.coords_m[0], [-2.4, -0.95, 0.0])
    assert g.lines[:3] == [(2, 5), (5, 6), (6, 3)] and len(g.lines) == 30
    assert any("type 18" in s for s in back.skipped)


# -------------------------------------------------------------------------------------------------------- HDF5

def test_h5_round_trip_is_exact(tmp_path, rec):
    attrs = {"capture": "plate_01", "n_averages": 5, "window": {"force": "rect", "response": "exp"}}
    path = write_results_h5(tmp_path / "results.h5", attrs=attrs, **rec)
    with h5py.File(path, "r") as f:
        assert (f.attrs["kind"], f.attrs["schema_version"]) == ("odsplat.results", 3)
        assert list(f["frfs"]) == ["H102", "H103", "H104"] and f["frfs/H102/values"].dtype == np.complex128
        assert f["shapes/mode 1/values"].shape == (6, 3) and f["time_series/hammer"].attrs["dt_s"] == DT_S
    back = read_results_h5(path)
    assert back.attrs == attrs
    g = back.geometry
    np.testing.assert_array_equal(g.node_ids, NODES)
    np.testing.assert_array_equal(g.coords_m, rec["geometry"].coords_m)
    assert g.lines == LINES and g.names == rec["geometry"].names
    for kind in ("time_series", "frfs", "shapes"):
        assert [r.name for r in getattr(back, kind)] == [r.name for r in rec[kind]]
        for got, want in zip(getattr(back, kind), rec[kind]):
            for key, value in vars(want).items():
                if isinstance(value, np.ndarray):
                    assert getattr(got, key).dtype == value.dtype
                    np.testing.assert_array_equal(getattr(got, key), value)
                else:
                    assert getattr(got, key) == value, (kind, key)


# ------------------------------------------------------------------------------------------------------ errors

def test_uneven_frf_axis_is_refused(tmp_path, rec):
    freq = np.array([0.0, 1.0, 2.0, 3.5, 4.0])
    with pytest.raises(InputError, match=r"FRF 'H_bad'.*freq_hz is not uniformly spaced"):
        FRFRecord("H_bad", 2, "+Z", 1, "-Z", "accelerance", freq, np.ones(5, complex))
    frf = rec["frfs"][0]
    frf.freq_hz = frf.freq_hz ** 1.01                    # records are mutable: the writers check again
    with pytest.raises(InputError, match=r"FRF 'H102'.*freq_hz"):
        write_uff(tmp_path / "bad.uff", frfs=[frf])
    assert not (tmp_path / "bad.uff").exists()


def test_shape_nodes_must_be_in_the_geometry(tmp_path, rec):
    stray = ShapeRecord("mode 3", 50.0, 0.01, [101, 102, 999], np.ones((3, 3), complex))
    for write, name in ((write_uff, "bad.uff"), (write_results_h5, "bad.h5")):
        with pytest.raises(InputError, match=r"shape 'mode 3'.*node_ids \[999\]"):
            write(tmp_path / name, geometry=rec["geometry"], shapes=[stray])
        assert not (tmp_path / name).exists()


def test_bad_records_name_the_field():
    with pytest.raises(InputError, match=r"time series 'acc'.*direction 'up' not recognised"):
        TimeSeries("acc", 3, "up", "acceleration", "m/s^2", 0.0, 1e-3, np.zeros(10))
    with pytest.raises(InputError, match=r"FRF 'H'.*reference_direction"):
        FRFRecord("H", 2, "+Z", 1, (0, 0, 0), "accelerance", [0.0, 1.0], [1j, 2j])
    with pytest.raises(InputError, match=r"time series 'acc'.*values holds 1 NaN"):
        TimeSeries("acc", 3, "+Y", "acceleration", "m/s^2", 0.0, 1e-3, [0.0, np.nan, 1.0])
    with pytest.raises(InputError, match=r"shape 'm'.*values must have shape"):
        ShapeRecord("m", 10.0, 0.01, [1, 2], np.ones((2, 2)))


def test_reading_a_file_that_is_not_uff(tmp_path, shared_data):
    text = tmp_path / "notes.uff"
    text.write_text("hammer hits at node 101, 5 averages\n")
    with pytest.raises(InputError, match="notes.uff: not a universal file"):
        read_uff(text)
    with pytest.raises(InputError, match="notes.uff: not an HDF5 file"):
        read_results_h5(text)
    with pytest.raises(InputError, match=r"1858.uff: holds no nodes.*\[1858\]"):
        read_uff(shared_data / "pyuff-samples" / "1858.uff")


# -------------------------------------------------------------------------------------------------- atomicity

def test_failed_write_leaves_no_partial_file(tmp_path, rec, monkeypatch):
    path = tmp_path / "results.uff"
    write_uff(path, geometry=rec["geometry"])
    before = path.read_bytes()

    def broken(fh, dset):
        fh.write("    -1\n    55\nhalf a dataset\n")
        raise RuntimeError("disk full")

    monkeypatch.setattr(pyuff.pyuff, "_write55", broken)  # fails after nodes, lines and functions are written
    with pytest.raises(OdsplatError, match="shape 'mode 1'.*disk full"):
        write_uff(path, **rec)
    assert path.read_bytes() == before
    with pytest.raises(OdsplatError):
        write_uff(tmp_path / "new.uff", **rec)
    with pytest.raises(TypeError):                         # h5py cannot store an object: fails mid-file
        write_results_h5(tmp_path / "new.h5", attrs={"bad": object()}, **rec)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["results.uff"]
