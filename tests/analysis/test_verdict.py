"""The MAC verdict can discriminate (analysis/verdict.py): on the arm rig's four accelerometers modes 3, 5 and 6 look
alike (reference AutoMAC above DISCRIMINATION), so even a perfect video is not "met" there; the video's full field
of the true shapes tells mode 6 from 3 and 5, not 3 from 5; modes the sensors separate stay "met". analysis.json
holds the matrices and the statuses, typed, and the report shows them. Ground truth: hil_sim's structure."""
from __future__ import annotations

import json
import re

import numpy as np
import pytest

from odsplat.analysis import read_analysis, write_report
from odsplat.analysis.correlation import auto_mac, mac
from odsplat.analysis.document import KIND, SCHEMA
from odsplat.analysis.verdict import (
    BELOW_FLOOR,
    DISCRIMINATION,
    FULL_FIELD_DISTINCT,
    MET,
    MIN_MAC,
    NOT_DISCRIMINATED,
    NOT_MET,
    NOT_SEPARATED,
    ModeStatus,
    mac_verdict,
)
from odsplat.hil_sim.rig import DEFAULT_ACCELEROMETERS, make_rig
from odsplat.hil_sim.structure import ModalStructure
from odsplat.spine.contract import describe, plain
from odsplat.spine.errors import InputError

from .test_report_safety import PAYLOADS, _analysis, _assert_inert, _capture, _poisoned


@pytest.fixture(scope="module")
def arm():
    """The arm rig's exact modes: at its four accelerometers along their directions (R, S), and over the truth's
    surface points (R, N, 3)."""
    structure = ModalStructure()
    pos = np.array([a.point_m for a in DEFAULT_ACCELEROMETERS], float)
    dirs = np.array([a.direction for a in DEFAULT_ACCELEROMETERS], float)
    sensors = np.einsum("prk,pk->rp", structure.mode_shapes(pos), dirs)
    surface = structure.mode_shapes(make_rig("arm").surface_points_m).transpose(1, 0, 2)
    return structure.freqs_hz, sensors, surface


def test_auto_mac_is_the_mac_of_a_set_with_itself_flattened(arm):
    _, sensors, surface = arm
    assert np.allclose(auto_mac(sensors), mac(sensors, sensors))
    flat = surface.reshape(len(surface), -1)
    assert np.allclose(auto_mac(surface), mac(flat, flat)) and np.allclose(np.diag(auto_mac(surface)), 1.0)
    with pytest.raises(InputError, match="at least one shape"):
        auto_mac(np.zeros((0, 4)))


def test_modes_3_5_6_are_not_met_at_four_sensors_even_with_a_perfect_video(arm):
    freq, sensors, _ = arm
    auto = auto_mac(sensors)
    for i, j in ((2, 4), (2, 5), (4, 5)):           # modes 3/5, 3/6, 5/6: 0.96, 0.99, 0.99 at the four sensors
        assert auto[i, j] > 0.95 > DISCRIMINATION
    perfect = np.diag(mac(sensors, sensors))          # the video's shapes exactly the reference's: MAC 1
    v = mac_verdict(freq, perfect, np.zeros(6, bool), reference_automac=auto)
    assert v.status == NOT_DISCRIMINATED and v.status != MET
    by_mode = {s.mode: s for s in v.modes}
    for k, others in ((3, {5, 6}), (5, {3, 6}), (6, {3, 5})):
        s = by_mode[k]
        assert s.status == NOT_DISCRIMINATED and s.mac == pytest.approx(1.0)
        assert others <= set(s.confused_with), s.confused_with
        assert all(a > DISCRIMINATION for a in s.automac)
        assert s.text.startswith("not discriminated: MAC 1.000, but the sensors cannot tell it from mode ")
        assert "(reference AutoMAC 0." in s.text and all(f"mode {o} (" in s.text for o in others)
    assert "but the sensors cannot tell modes" in v.line and "3/5 0.96" in v.line and "3/6 0.99" in v.line
    assert v.details["not_discriminated_hz"] == [s.freq_hz for s in v.modes if s.status == NOT_DISCRIMINATED]


def test_the_full_field_of_the_true_shapes_tells_mode_6_from_3_and_5_not_3_from_5(arm):
    freq, sensors, surface = arm
    cross = auto_mac(surface)
    assert cross[2, 5] < 0.05 and cross[4, 5] < 0.05 and cross[2, 4] > 0.8     # 0.000, 0.030; 0.857
    v = mac_verdict(freq, np.ones(6), np.zeros(6, bool), reference_automac=auto_mac(sensors), video_cross_mac=cross)
    assert v.status == NOT_DISCRIMINATED
    s6 = next(s for s in v.modes if s.mode == 6)
    ff = dict(zip(s6.confused_with, s6.full_field_mac))
    assert ff[3] == pytest.approx(cross[5, 2]) and ff[5] == pytest.approx(cross[5, 4])
    assert all(c < FULL_FIELD_DISTINCT for c in ff.values())
    assert s6.text.endswith("the video's full field tells it from mode 1 (cross-MAC 0.021), mode 3 (0.000), mode 5 "
                            "(0.030)"), s6.text
    s3 = next(s for s in v.modes if s.mode == 3)
    assert "not from mode 5 (0.857)" in s3.text, s3.text
    assert "3/6 (0.000)" in v.line and "5/6 (0.030) apart" in v.line and ", not " in v.line and "3/5 (0.857)" in v.line


def test_a_partner_below_the_floor_is_no_evidence_and_stays_not_discriminated(arm):
    """Modes 2 and 4 look alike at the sensors (0.83); with 4 below the video's noise floor its full-field shape is
    noise, so its low cross-MAC with 2 says nothing: 2 stays not discriminated, 4 below floor."""
    freq, sensors, surface = arm
    below = np.array([False, False, False, True, False, False])
    v = mac_verdict(freq, np.ones(6), below, reference_automac=auto_mac(sensors), video_cross_mac=np.eye(6))
    s2, s4 = v.modes[1], v.modes[3]
    assert s4.status == BELOW_FLOOR and v.details["below_floor_hz"] == [142.0]
    assert s2.status == NOT_DISCRIMINATED and s2.confused_with == (4,) and s2.confused_below_floor == (True,)
    assert s2.text.endswith("; mode 4 is below the video's noise floor (the full-field shape there is noise)")
    assert "tells it from" not in s2.text and "2/4: one mode below the video's noise floor" in v.line


def test_modes_the_sensors_separate_stay_met_and_a_low_mac_is_not_met(arm):
    freq, sensors, _ = arm
    two = [0, 1]                                        # column bending x and y + twist: AutoMAC 0.000
    auto = auto_mac(sensors[two])
    assert auto[0, 1] < 0.01
    v = mac_verdict(freq[two], [0.995, 0.97], [False, False], reference_automac=auto, modes=[1, 2])
    assert v.status == MET and [s.status for s in v.modes] == [MET, MET] and v.modes[0].confused_with == ()
    assert v.line.startswith(f"MAC >= {MIN_MAC:g} for all 2 modes") and "cannot tell" not in v.line
    low = mac_verdict(freq[two], [0.995, 0.7], [False, False], reference_automac=auto, modes=[1, 2])
    assert low.status == NOT_MET and [s.status for s in low.modes] == [MET, NOT_MET]
    # one not met decides, whatever the others' discrimination
    mixed = mac_verdict(freq, [1, 1, 0.5, 1, 1, 1], np.zeros(6, bool), reference_automac=auto_mac(sensors))
    assert mixed.status == NOT_MET and mixed.modes[2].status == NOT_MET and "86.0 Hz (0.500)" in mixed.line
    # among modes 1-3 the sensors tell 2 from both others (AutoMAC 0.000), not 1 from 3 (0.87): 2 alone is met
    three = mac_verdict(freq[:3], np.ones(3), np.zeros(3, bool), reference_automac=auto_mac(sensors[:3]))
    assert three.status == NOT_DISCRIMINATED
    assert [s.status for s in three.modes] == [NOT_DISCRIMINATED, MET, NOT_DISCRIMINATED]
    assert three.modes[0].confused_with == (3,) and three.modes[2].confused_with == (1,)
    assert "cannot tell modes 1, 3 from others (reference AutoMAC above 0.5: 1/3 0.87)" in three.line


def test_without_the_automac_the_verdict_reads_as_before():
    v = mac_verdict([23.5, 31.0, 86.0], [0.99, 0.95, 0.3], [False, False, True])
    assert v.status == MET and v.modes == () and "discrimination" not in v.details
    assert v.line == ("MAC >= 0.9 for all 2 modes above the video's noise floor (lowest 0.950 at 31.0 Hz); below "
                      "the video's noise floor, not judged: 86.0 Hz (MAC 0.30)")
    with pytest.raises(InputError, match="reference_automac"):
        mac_verdict([1.0, 2.0], [1, 1], [False, False], reference_automac=np.eye(3))


def test_a_pair_the_record_cannot_separate_is_not_judged_whatever_its_mac():
    """The mast's pair at 400 px (docs/fidelity.md): above the floor, MAC 0.74 and 0.50 at the sensors with full-field
    shapes 2-3x too large; not separated by the record, so neither met nor not met, and the line says why."""
    auto = np.array([[1.0, 0.1, 0.0], [0.1, 1.0, 0.0], [0.0, 0.0, 1.0]])
    v = mac_verdict([40.8, 42.1, 255.9], [0.74, 0.50, 0.99], [False, False, False], reference_automac=auto,
                    unseparated=[True, True, False])
    assert v.status == MET and [s.status for s in v.modes] == [NOT_SEPARATED, NOT_SEPARATED, MET]
    assert v.details["judged_hz"] == [255.9] and v.details["not_separated_hz"] == [40.8, 42.1]
    assert v.line.startswith("MAC >= 0.9 for all 1 modes above the video's noise floor and separated")
    assert "too close to a mode beside them for the video's record to separate, not judged: 40.8 Hz (MAC 0.74)" \
        in v.line
    assert v.modes[0].text.startswith("not separated from a mode beside it")
    none = mac_verdict([40.8, 42.1], [0.74, 0.50], [False, True], unseparated=[True, True])
    assert none.status == "not judged" and none.details["not_separated_hz"] == [40.8]   # below the floor first
    assert none.line.startswith("MAC: no mode above the video's noise floor is separated by its record")


# ---------------------------------------------------------------------------------------------- the document

STATUSES = [ModeStatus(1, 23.5, 0.99, MET),
            ModeStatus(2, 31.0, 0.97, NOT_DISCRIMINATED, (3,), (0.96,), (0.12,), (True,)),
            ModeStatus(3, 86.0, 0.7, BELOW_FLOOR, (2,), (0.96,), (0.12,), (False,))]
MATRICES = {"mac_matrix": [[0.99, 0.02, 0.5], [0.01, 0.97, 0.96], [0.4, 0.95, 0.7]],
            "reference_automac": [[1.0, 0.01, 0.02], [0.01, 1.0, 0.96], [0.02, 0.96, 1.0]],
            "video_cross_mac": [[1.0, 0.03, 0.01], [0.03, 1.0, 0.12], [0.01, 0.12, 1.0]]}


def _document(capture) -> dict:
    """test_report_safety's analysis.json, schema 3: the verdict per mode and the three matrices."""
    data = {**_analysis(capture), **describe(capture.id, KIND, SCHEMA, {}).header()}
    verdict = mac_verdict([23.5, 31.0, 86.0], [0.99, 0.97, 0.7], [False, False, True],
                          reference_automac=MATRICES["reference_automac"],
                          video_cross_mac=MATRICES["video_cross_mac"])
    data["correlation"].update(verdict=plain(verdict.summary()),
                               **MATRICES)
    return data


def test_the_document_holds_the_statuses_and_matrices_typed_and_reads_back_equal(tmp_path):
    capture = _capture(tmp_path / "cap")
    data = _document(capture)
    capture.paths.analysis_json.write_text(json.dumps(data))
    doc = read_analysis(capture)
    c = doc.correlation
    assert c.verdict.status == NOT_DISCRIMINATED and c.verdict.modes[1].confused_with == (3,)
    assert all(isinstance(s, ModeStatus) for s in c.verdict.modes) and c.reference_automac[1][2] == 0.96
    assert doc.to_json() == data
    doc.write(capture)
    assert read_analysis(capture) == doc
    bad = json.loads(json.dumps(data))
    bad["correlation"]["verdict"]["modes"][0]["mac"] = "high"
    capture.paths.analysis_json.write_text(json.dumps(bad))
    with pytest.raises(InputError) as err:
        read_analysis(capture)
    assert err.value.source.endswith("correlation.verdict.modes[0].mac")


def test_a_schema_2_file_still_reads_without_them(tmp_path):
    capture = _capture(tmp_path / "cap")
    data = _analysis(capture)                          # schema 2, as written before
    capture.paths.analysis_json.write_text(json.dumps(data))
    doc = read_analysis(capture)
    assert doc.provenance.schema_version == 2 and doc.correlation.reference_automac is None
    assert doc.correlation.verdict.modes == () and doc.to_json() == data
    html = write_report(capture).read_text()
    assert "MAC matrices" not in html and "<th>status</th>" not in html


# ---------------------------------------------------------------------------------------------- the report

def test_the_report_shows_the_matrices_and_each_modes_status_in_words(tmp_path):
    capture = _capture(tmp_path / "cap")
    capture.paths.analysis_json.write_text(json.dumps(_document(capture)))
    html = write_report(capture).read_text()
    assert '<p id="verdict" class="warn"><b>Verdict:</b> MAC &gt;= 0.9 for all 2 modes' in html
    assert "MAC matrices" in html and "MAC: accelerometers (rows) vs video (columns)" in html
    assert "AutoMAC, accelerometers" in html and "Cross-MAC, video full field" in html
    # the AutoMAC's 2/3 cell, outlined (the sensors cannot tell them apart), and the MAC matrix's labels
    assert html.count('<td class="h9 over">0.96</td>') == 2 and "<th>a 2</th>" in html and "<th>b 3</th>" in html
    assert '<td class="h1">0.12</td>' in html                      # the full field: apart, not outlined
    summary = html[html.index('<section id="summary">'):html.index("</section>")]
    assert '<span class="ok">met</span>' in summary and '<span class="warn">not discriminated</span>' in summary
    assert re.search(r'<tr class="grey"><td class="t">3</td>.*?below the noise floor: not judged</td></tr>', summary)
    assert ("not discriminated: MAC 0.970, but the sensors cannot tell it from mode 3 (reference AutoMAC 0.96), so "
            "the MAC does not show its shape; mode 3 is below the video&#x27;s noise floor") in html
    assert "met: MAC 0.990, and the sensors tell it from every other mode" in html


@pytest.mark.parametrize("payload", PAYLOADS)
def test_the_statuses_show_as_text_whatever_the_file_holds(tmp_path, payload):
    capture = _capture(tmp_path / "cap")
    data = _poisoned(_document(capture), payload)
    capture.paths.analysis_json.write_text(json.dumps(data))
    html = write_report(capture).read_text()
    text = "".join(_assert_inert(html).texts)          # no tag of the payload's, no attribute it made
    for path in (".correlation.verdict.modes[1].status", ".correlation.verdict.line"):
        assert f"{payload} {path}" in text, path
