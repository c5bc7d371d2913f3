"""Tests of odsplat.spine.io.signals: real LVM and UFF recordings, and CSV/LVM/UFF files written here with
known values."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import pyuff

from odsplat.spine.errors import InputError
from odsplat.spine.io.signals import read_signals
from odsplat.spine.units import STANDARD_GRAVITY_M_S2 as G

# --- real recordings ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("name, first_g, first_n, last_g, last_n", [
    ("acceleration.lvm", -0.007387, 0.232147, -0.009162, 0.298803),
    ("camera.lvm", -0.012509, -0.029330, None, None),
])
def test_ladisk_lvm(shared_data: Path, name, first_g, first_n, last_g, last_n):
    signals = read_signals(shared_data / "ladisk-imaging-tutorial" / name)
    assert signals.sample_rate_hz == pytest.approx(50_000.0, rel=1e-12)
    assert signals.t0_s == 0.0
    assert signals.n_samples == 50_030
    assert [c.name for c in signals.channels] == ["Acceleration (Trigger)", "Force (Trigger)"]
    acc, force = signals.channel("Acceleration (Trigger)"), signals.channel("Force (Trigger)")
    assert (acc.unit, acc.source_unit, force.unit, force.source_unit) == ("m/s^2", "g", "N", "Newtons")
    assert acc.values.dtype == np.float32 and acc.values.shape == (50_030,)
    assert acc.values[0] == pytest.approx(first_g * G, rel=1e-6)
    assert force.values[0] == pytest.approx(first_n, rel=1e-6)
    if last_g is not None:
        assert acc.values[-1] == pytest.approx(last_g * G, rel=1e-6)
        assert force.values[-1] == pytest.approx(last_n, rel=1e-6)


@pytest.mark.parametrize("name", ["acceleration.lvm", "camera.lvm"])
def test_ladisk_lvm_equals_lvm_read(shared_data: Path, name):
    """lvm-read (LADISK's reader) parses the same files to the same numbers, rates and units."""
    lvm_read = pytest.importorskip("lvm_read")
    path = shared_data / "ladisk-imaging-tutorial" / name
    reference = lvm_read.read(str(path), read_from_pickle=False, dump_file=False)  # no .pkl beside the file
    segment = reference[0]
    assert reference["Segments"] == 1
    signals = read_signals(path)
    assert signals.sample_rate_hz == pytest.approx(1.0 / segment["Delta_X"][0], rel=1e-12)
    assert signals.t0_s == segment["X0"][0]
    assert [c.name for c in signals.channels] == segment["Channel names"][:2]
    assert [c.source_unit for c in signals.channels] == segment["Y_Unit_Label"][:2]
    assert signals.n_samples == segment["Samples"][0] == len(segment["data"])
    for k, channel in enumerate(signals.channels):
        expected = segment["data"][:, k] * (G if channel.source_unit == "g" else 1.0)
        np.testing.assert_array_equal(channel.values, expected.astype(np.float32))


def test_lvm_columns_select_and_missing(shared_data: Path):
    path = shared_data / "ladisk-imaging-tutorial" / "acceleration.lvm"
    signals = read_signals(path, columns=["Force (Trigger)"])
    assert [c.name for c in signals.channels] == ["Force (Trigger)"]
    assert signals.channels[0].values[0] == pytest.approx(0.232147, rel=1e-6)
    with pytest.raises(InputError) as err:
        read_signals(path, columns=["Velocity"])
    assert "acceleration.lvm" in str(err.value) and "'Velocity'" in str(err.value)
    assert "Acceleration (Trigger)" in str(err.value)
    with pytest.raises(InputError, match="no channel 'Velocity'"):
        signals.channel("Velocity")


def test_uff58b_mpstd(shared_data: Path):
    signals = read_signals(shared_data / "pyuff-samples" / "MPSTD#Set001_2024_10_08_10_27_07.uff")
    assert len(signals.channels) == 4
    assert signals.sample_rate_hz == pytest.approx(3200.0, rel=1e-9)
    assert signals.n_samples / signals.sample_rate_hz == pytest.approx(69.5, rel=1e-9)
    assert signals.t0_s == 0.0
    assert {c.unit for c in signals.channels} == {"m/s^2"}
    assert len({c.name for c in signals.channels}) == 4
    dof1 = signals.channel("MPS set1 Dof1")
    assert dof1.source_unit == "m/s2"
    assert dof1.values[0] == pytest.approx(0.08014834, rel=1e-6)
    assert all(np.isfinite(c.values).all() for c in signals.channels)


def test_uff58_ascii_and_binary_agree(shared_data: Path):
    ascii_ = read_signals(shared_data / "pyuff-samples" / "Sample_UFF58_ascii.uff")
    binary = read_signals(shared_data / "pyuff-samples" / "Sample_UFF58b_bin.uff")
    for signals in (ascii_, binary):
        assert signals.sample_rate_hz == pytest.approx(1 / 1.52588e-5, rel=1e-9)  # 2**16 Hz, dt printed to 6 digits
        assert signals.n_samples == 79_292
        (mic,) = signals.channels
        assert (mic.name, mic.unit, mic.source_unit) == ("Mic 01.0Scalar", "Pa", "Pa")
        assert np.isfinite(mic.values).all()
    # The ASCII file holds the same microphone record printed to 6 significant digits.
    a, b = ascii_.channels[0].values, binary.channels[0].values
    assert a[0] == pytest.approx(-1.47553e-2, rel=1e-6)
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-5 * np.abs(b).max())


def test_uff_psd_is_refused(shared_data: Path):
    with pytest.raises(InputError) as err:
        read_signals(shared_data / "pyuff-samples" / "sample_dataset58_psd.uff")
    message = str(err.value)
    assert "sample_dataset58_psd.uff" in message and "time series" in message and "[9]" in message


# --- UFF written here --------------------------------------------------------------------------------------


def _write_uff(path: Path, records: list[tuple[str, float, np.ndarray]]) -> None:
    """Write (id1, dt, values) records, all at response node 1, direction +Z, in g."""
    uff = pyuff.UFF(str(path))
    for id1, dt, values in records:
        uff.write_sets(pyuff.prepare_58(
            binary=0, id1=id1, func_type=1, rsp_node=1, rsp_dir=3, ref_node=0, ref_dir=0, abscissa_spacing=1,
            abscissa_spec_data_type=17, ordinate_spec_data_type=12, orddenom_spec_data_type=0, z_axis_spec_data_type=0,
            ordinate_axis_units_lab="g", data=values, x=np.arange(len(values)) * dt), mode="add")


def test_uff_names_made_unique_and_clock_checked(tmp_path: Path):
    path = tmp_path / "two.uff"
    ramp = np.arange(16, dtype=float)
    _write_uff(path, [("NONE", 1e-3, ramp), ("NONE", 1e-3, 2 * ramp), ("hammer", 1e-3, 3 * ramp)])
    signals = read_signals(path)
    assert [c.name for c in signals.channels] == ["rsp_node1_dir3_1", "rsp_node1_dir3_2", "hammer"]
    assert signals.sample_rate_hz == pytest.approx(1000.0)
    np.testing.assert_allclose(signals.channel("rsp_node1_dir3_2").values, 2 * ramp * G, rtol=1e-6)

    mixed = tmp_path / "mixed.uff"
    _write_uff(mixed, [("a", 1e-3, ramp), ("b", 2e-3, ramp)])
    with pytest.raises(InputError, match=r"mixed\.uff: time records do not share one sample clock"):
        read_signals(mixed)


# --- CSV written here ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("sep", [",", ";", "\t"])
def test_csv_round_trip(tmp_path: Path, sep: str):
    fs, f0, n = 1000.0, 50.0, 200
    t_ms = 5.0 + np.arange(n) * 1000.0 / fs
    force_n = 10.0 * np.cos(2 * np.pi * f0 * t_ms / 1000.0)
    acc_g = 0.5 * np.sin(2 * np.pi * f0 * t_ms / 1000.0)
    lines = ["# hammer hit 3, rig A", sep.join(["t (ms)", "force [N]", "acc1 (g)"])]
    lines += [sep.join(f"{v:.9g}" for v in row) for row in zip(t_ms, force_n, acc_g)]
    path = tmp_path / "hit.csv"
    path.write_text("\n".join(lines) + "\n")

    signals = read_signals(path)
    assert signals.sample_rate_hz == pytest.approx(fs, rel=1e-9)
    assert signals.t0_s == pytest.approx(0.005, rel=1e-12)
    assert signals.n_samples == n
    force, acc = signals.channels
    assert (force.name, force.unit, force.source_unit) == ("force", "N", "N")
    assert (acc.name, acc.unit, acc.source_unit) == ("acc1", "m/s^2", "g")
    np.testing.assert_allclose(force.values, force_n, rtol=0, atol=1e-5)
    np.testing.assert_allclose(acc.values, acc_g * G, rtol=0, atol=1e-5)
    assert not acc.values.flags.writeable

    swapped = read_signals(path, columns=["acc1", "force"], units={"force": "kN"})
    assert [c.name for c in swapped.channels] == ["acc1", "force"]
    np.testing.assert_allclose(swapped.channel("force").values, force_n * 1e3, rtol=1e-6)


def test_csv_rounded_timestamps_are_not_jitter(tmp_path: Path):
    # 3 kHz printed to 6 decimals: steps read 0.000333 and 0.000334, 3e-3 apart, yet the clock is uniform.
    t = np.arange(300) / 3000.0
    path = tmp_path / "daq.txt"
    path.write_text("time [s],p [Pa]\n" + "".join(f"{x:.6f},{k}\n" for k, x in enumerate(t)))
    signals = read_signals(path)
    assert signals.sample_rate_hz == pytest.approx(3000.0, rel=1e-5)
    np.testing.assert_array_equal(signals.channel("p").values, np.arange(300, dtype=np.float32))


_GOOD = ["# rig A", "time [s],force [N],acc (g)"] + [f"{k * 0.001:.3f},{k + 1}.0,0.{k + 1}" for k in range(10)]


def _csv(tmp_path: Path, lines: list[str], name: str = "bad.csv") -> Path:
    path = tmp_path / name
    path.write_text("\n".join(lines) + "\n")
    return path


def _replace(line_no: int, text: str | None) -> list[str]:
    """_GOOD with 1-based line `line_no` replaced (or removed when text is None)."""
    lines = list(_GOOD)
    if text is None:
        del lines[line_no - 1]
    else:
        lines[line_no - 1] = text
    return lines


@pytest.mark.parametrize("lines, expected", [
    (_replace(5, "0.002,3.0"), ["line 5", "'acc'", "missing"]),  # ragged row
    (_replace(5, "0.002,abc,0.3"), ["line 5", "'force'", "'abc'"]),
    (_replace(5, "0.002,nan,0.3"), ["line 5", "'force'", "'nan'"]),
    (_replace(5, "0.002,,0.3"), ["line 5", "'force'", "empty"]),
    (_replace(6, "0.001,4.0,0.4"), ["line 6", "does not increase"]),
    (_replace(6, None), ["line 6", "not uniformly sampled"]),  # a dropped sample
    (_replace(6, "0.0030500,4.0,0.4"), ["line 6", "not uniformly sampled"]),  # 5 % jitter
    (_replace(2, "time [s],force [N],acc (furlong)"), ["'acc'", "unknown unit 'furlong'"]),
    (_replace(2, "time [s],force [N],acc"), ["'acc'", "no unit"]),
    (_replace(2, "x [s],force [N],acc (g)"), ["first column must be time"]),
    (_GOOD[:3], ["only 1 data row"]),
], ids=["ragged", "non-numeric", "nan", "empty", "non-monotonic", "dropped-sample", "jitter", "unknown-unit",
        "missing-unit", "no-time", "one-row"])
def test_csv_bad_input(tmp_path: Path, lines: list[str], expected: list[str]):
    with pytest.raises(InputError) as err:
        read_signals(_csv(tmp_path, lines))
    message = str(err.value)
    assert message.startswith(str(tmp_path / "bad.csv") + ": ")
    assert "\n" not in message
    for part in expected:
        assert part in message


def test_csv_unit_given_by_caller(tmp_path: Path):
    signals = read_signals(_csv(tmp_path, _replace(2, "time [s],force [N],acc")), units={"acc": "g"})
    acc = signals.channel("acc")
    assert (acc.unit, acc.source_unit) == ("m/s^2", "g")
    assert acc.values[0] == pytest.approx(0.1 * G, rel=1e-6)
    with pytest.raises(InputError, match=r"units given for \['accel'\]"):
        read_signals(_csv(tmp_path, _GOOD), units={"accel": "g"})


def test_unsupported_suffix_and_missing_file(tmp_path: Path):
    with pytest.raises(InputError, match=r"take\.mat: unsupported suffix '\.mat'; expected one of .*\.lvm"):
        read_signals(tmp_path / "take.mat")
    with pytest.raises(InputError, match=r"absent\.csv: no such file"):
        read_signals(tmp_path / "absent.csv")


# --- LVM written here ---------------------------------------------------------------------------------------


def _write_lvm(path: Path, segments: list[tuple[float, np.ndarray]], *, sep: str = "\t", decimal: str = ".",
               x_columns: str = "No", newline: str = "\n", dt: float = 1e-3, names=("Force", "Acc"),
               units=("Newtons", "g")) -> None:
    """Write an LVM 2 file like LabVIEW's: each segment is (X0, values of shape (n, channels))."""
    def num(x: float, fmt: str = ".6f") -> str:
        return format(x, fmt).replace(".", decimal)

    heading = ["X_Value"]
    for name in names:
        heading += ["X_Value", name] if x_columns == "Multi" and len(heading) > 1 else [name]
    heading.append("Comment")

    def per_channel(tag: str, values: list[str]) -> str:
        it = iter(values)
        return sep.join([tag] + [next(it) if h in names else "" for h in heading[1:-1]])

    header = ["LabVIEW Measurement", "Writer_Version" + sep + "2", "Separator" + sep + {"\t": "Tab", ",": "Comma"}[sep],
              "Decimal_Separator" + sep + decimal, "Multi_Headings" + sep + "Yes", "X_Columns" + sep + x_columns,
              "***End_of_Header***", ""]
    lines = header
    for x0, values in segments:
        n = len(names)
        lines += [sep.join(["Channels", str(n)]), per_channel("Samples", [str(len(values))] * n),
                  per_channel("Y_Unit_Label", list(units)), per_channel("X_Dimension", ["Time"] * n),
                  per_channel("X0", [num(x0, ".16E")] * n), per_channel("Delta_X", [num(dt, "E")] * n),
                  "***End_of_Header***", sep.join(heading)]
        for k, row in enumerate(values):
            x = num(x0 + k * dt)
            fields = {"No": [""], "One": [x], "Multi": [x]}[x_columns] + [num(row[0])]
            for v in row[1:]:
                fields += [x, num(v)] if x_columns == "Multi" else [num(v)]
            lines.append(sep.join(fields))
        lines.append("")
    path.write_text("\n".join(lines) + "\n", newline=newline)


def _known(n: int) -> np.ndarray:
    k = np.arange(n)
    return np.column_stack([np.round(np.sin(0.3 * k), 6), np.round(0.01 * k - 0.2, 6)])


@pytest.mark.parametrize("sep, decimal, x_columns, newline", [
    (",", ".", "One", "\n"), ("\t", ",", "No", "\r\n"), ("\t", ".", "Multi", "\n"),
])
def test_lvm_layouts(tmp_path: Path, sep: str, decimal: str, x_columns: str, newline: str):
    values = _known(40)
    path = tmp_path / "hit.lvm"
    _write_lvm(path, [(0.25, values)], sep=sep, decimal=decimal, x_columns=x_columns, newline=newline)
    signals = read_signals(path)
    assert signals.sample_rate_hz == pytest.approx(1000.0, rel=1e-9)
    assert signals.t0_s == pytest.approx(0.25)
    assert [(c.name, c.unit, c.source_unit) for c in signals.channels] == [("Force", "N", "Newtons"),
                                                                          ("Acc", "m/s^2", "g")]
    np.testing.assert_allclose(signals.channel("Force").values, values[:, 0], rtol=0, atol=1e-6)
    np.testing.assert_allclose(signals.channel("Acc").values, values[:, 1] * G, rtol=0, atol=1e-6)


def test_lvm_segments(tmp_path: Path):
    values = _known(30)
    path = tmp_path / "two.lvm"
    _write_lvm(path, [(0.0, values[:20]), (0.020, values[20:])])
    signals = read_signals(path)
    assert signals.n_samples == 30
    np.testing.assert_allclose(signals.channel("Force").values, values[:, 0], rtol=0, atol=1e-6)

    gap = tmp_path / "gap.lvm"
    _write_lvm(gap, [(0.0, values[:20]), (0.5, values[20:])])
    with pytest.raises(InputError, match=r"gap\.lvm: segment 2 starts at X0 = 0\.5, not at 0\.02"):
        read_signals(gap)


@pytest.mark.parametrize("newline", ["\n", "\r\n"])
def test_lvm_bad_cell_names_line(tmp_path: Path, newline: str):
    path = tmp_path / "bad.lvm"
    _write_lvm(path, [(0.0, _known(10))])
    lines = path.read_text().splitlines()
    row = lines.index("X_Value\tForce\tAcc\tComment") + 4  # 0-based index of the 4th data row
    lines[row] = "\t0.5\tclipped"
    path.write_text("\n".join(lines) + "\n", newline=newline)
    with pytest.raises(InputError) as err:
        read_signals(path)
    assert str(err.value) == f"{path}: line {row + 1}: column 'Acc' holds 'clipped', not a number"


@pytest.mark.parametrize("heading, scale", [("time_s", 1.0), ("Time [ms]", 1e-3), ("t_ms", 1e-3),
                                            ("timestamp (s)", 1.0), ("TIME", 1.0), ("t_us", 1e-6)])
def test_csv_time_column_by_its_common_names(tmp_path: Path, heading: str, scale: float):
    path = tmp_path / "hit.csv"
    t = np.arange(50) * 1e-3 / scale             # 1 kHz, in the column's unit
    path.write_text(f"{heading},force [N]\n" + "".join(f"{float(x)!r},{k}\n" for k, x in enumerate(t)))
    signals = read_signals(path)
    assert signals.sample_rate_hz == pytest.approx(1000.0, rel=1e-9)
    with pytest.raises(InputError, match="first column must be time"):
        path.write_text("time_kg,force [N]\n0,1\n1,2\n")
        read_signals(path)


def test_seven_digit_time_stamps_give_one_rate_to_a_part_in_a_million(tmp_path: Path):
    """20480 Hz printed to 7 significant digits: two takes read 20479.99808 and 20479.9994 Hz; the importer
    takes them as one clock (odsplat.spine.importer.RATE_TOLERANCE)."""
    rates = []
    for n in (20480, 20000):
        path = tmp_path / f"take{n}.csv"
        t = np.arange(n) / 20480.0
        path.write_text("time_s,acc [m/s^2]\n" + "".join(f"{x:.7g},{k % 7}\n" for k, x in enumerate(t)))
        rates.append(read_signals(path).sample_rate_hz)
    assert rates[0] != rates[1] and abs(rates[0] / rates[1] - 1) < 1e-6
