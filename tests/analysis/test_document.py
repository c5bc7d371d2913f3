"""analysis.json as one typed record (analysis/document.py): what is written reads back equal, the file holds the keys
and values the analysis has always written, and a hand edit of the wrong kind in any section is refused in one line
naming the field, by read_analysis and so by every reader (the report, the viewer, the demo)."""
from __future__ import annotations

import dataclasses
import json

import pytest

from odsplat.analysis import AnalysisDocument, read_analysis, write_report
from odsplat.analysis.document import VideoSection
from odsplat.spine.errors import InputError

from .test_report_safety import _analysis, _capture


def test_a_written_document_reads_back_equal_and_holds_the_files_keys(tmp_path):
    capture = _capture(tmp_path / "cap")
    data = _analysis(capture)
    capture.paths.analysis_json.write_text(json.dumps(data))
    doc = read_analysis(capture)
    assert doc.to_json() == data                          # every key and value, none added or lost
    assert doc.video.noise_floor.modes[2].below_floor and doc.correlation.pairs[1].expected_mac == 0.07
    assert doc.video.crosscheck[0].expected_correlation == pytest.approx(0.4 / (0.4**2 + 0.01**2) ** 0.5)
    assert doc.pair_by_mode()[2].mac == 0.7 and doc.structure_settings() == {}
    again = dataclasses.replace(doc, notes=("a note",), video=dataclasses.replace(doc.video, real_modes=None))
    again.write(capture)
    back = read_analysis(capture)
    assert back == again and back != doc and back.video.real_modes is None
    assert "real_modes" not in json.loads(capture.paths.analysis_json.read_text())["video"]


def test_sections_the_analysis_did_not_compute_are_absent_and_read_as_none(tmp_path):
    capture = _capture(tmp_path / "cap")
    data = _analysis(capture)
    for key in ("video", "image_poles", "correlation", "ods"):
        del data[key]
    data["settings"]["structure_box_m"] = [[0.0, -0.1, 0.02], [0.5, 0.1, 0.8]]
    capture.paths.analysis_json.write_text(json.dumps(data))
    doc = read_analysis(capture)
    assert doc.video is None and doc.image_poles is None and doc.correlation is None and doc.ods == ()
    assert doc.to_json() == data and doc.pair_by_mode() == {}
    assert doc.structure_settings() == {"structure_box_m": ((0.0, -0.1, 0.02), (0.5, 0.1, 0.8))}
    assert "No video side in this analysis." in write_report(capture).read_text()


def test_an_older_file_without_the_later_fields_still_reads(tmp_path):
    """The background's numbers and the floor's MAC came into schema 2 after its first files: their absence reads
    as their defaults, and the report gives the floor's MAC from its sigmas."""
    capture = _capture(tmp_path / "cap")
    data = _analysis(capture)
    for key in ("n_background_points", "structure_rule", "background_rms_um", "background_amplitude_um",
                "background_amplitude_ratio", "background_amplitude_ratio_all", "n_background_reference_points"):
        del data["video"][key]
    del data["video"]["noise_floor"]["floor_mac"]
    capture.paths.analysis_json.write_text(json.dumps(data))
    doc = read_analysis(capture)
    assert doc.video == VideoSection(**{**{f.name: getattr(doc.video, f.name)
                                           for f in dataclasses.fields(VideoSection)},
                                        "n_background_points": 0, "structure_rule": ""})
    assert doc.video.noise_floor.floor_mac is None
    assert "the noise alone would still allow its shape a MAC of 0.90." in write_report(capture).read_text()  # 9 / 10


# One field per section, edited by hand to the wrong kind (or removed): the path read_analysis must name.
WRONG = [
    ("n_averages", "two", "expected an integer"),
    ("exp_tau_s", "3 ms", "expected a number"),
    ("band_hz", [5.0], "expected a list of 2 values"),
    ("takes", "t1", "expected a list"),
    ("notes[0]", 5, "expected a string"),
    ("rejected_hits[1].reasons", "late", "expected a list"),
    ("modes[1].damping", True, "expected a number"),
    ("video", [], "expected an object"),
    ("video.modes_fitted[0]", 0.5, "expected an integer"),
    ("video.window_s", None, "missing"),
    ("video.crosscheck[0].n_points", "many", "expected an integer"),
    ("video.noise_floor.sigma_um", "5 um", "expected a number"),
    ("video.noise_floor.modes[0].below_floor", "no", "expected true or false"),
    ("video.real_modes[1].real", 1, "expected true or false"),
    ("video.crosscheck_verdict.line", 3, "expected a string"),
    ("image_poles.n_views", "3", "expected an integer"),
    ("correlation.pairs[0].mac", "high", "expected a number"),
    ("correlation.comac[1]", None, "expected a number"),
    ("correlation.verdict.status", ["met"], "expected a string"),
    ("ods[0].freq_hz", {"hz": 23.5}, "expected a number"),
    ("files.frf", 3, "expected a string"),
    ("settings.structure_box_m", [[0, 0, 0]], "expected a list of 2 values"),
]


def _edit(data: dict, field: str, value) -> None:
    """Sets (or, for None where the field must be missing, removes) the field at a path like "video.crosscheck[0].n"."""
    keys = [int(k) if k.isdigit() else k for k in field.replace("[", ".").replace("]", "").split(".")]
    target = data
    for k in keys[:-1]:
        target = target[k]
    if value is None and field == "video.window_s":
        del target[keys[-1]]
    else:
        target[keys[-1]] = value


@pytest.mark.parametrize("field, value, problem", WRONG, ids=[w[0] for w in WRONG])
def test_a_field_of_the_wrong_kind_is_refused_in_one_line_naming_it(tmp_path, field, value, problem):
    capture = _capture(tmp_path / "cap")
    data = _analysis(capture)
    _edit(data, field, value)
    capture.paths.analysis_json.write_text(json.dumps(data))
    with pytest.raises(InputError) as err:
        read_analysis(capture)
    assert err.value.source == f"{capture.paths.analysis_json}: {field}"
    assert err.value.problem.startswith(problem), err.value.problem
    assert "\n" not in str(err.value)
    with pytest.raises(InputError, match=field.replace("[", r"\[").replace("]", r"\]")):
        write_report(capture)
    assert not capture.paths.report_html.exists()


def test_from_json_checks_the_header_and_the_capture_only_where_given(tmp_path):
    capture = _capture(tmp_path / "cap")
    data = _analysis(capture)
    doc = AnalysisDocument.from_json(json.loads(json.dumps(data)), "memory")     # no capture to check against
    assert doc.provenance.capture_id == capture.id and doc.capture == "bench-arm"
    with pytest.raises(InputError, match="belongs to another capture"):
        AnalysisDocument.from_json(data, "memory", capture_id="another")
    with pytest.raises(InputError, match="schema 4 is newer"):
        AnalysisDocument.from_json({**data, "schema_version": 4}, "memory")
    with pytest.raises(InputError, match="schema 1 is older"):
        AnalysisDocument.from_json({**data, "schema_version": 1}, "memory")
    with pytest.raises(InputError) as err:
        AnalysisDocument.from_json({k: v for k, v in data.items() if k != "created_utc"}, "memory")
    assert str(err.value) == "memory: created_utc: missing"
