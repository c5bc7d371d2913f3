"""derived/qc.json has one format and one reader (odsplat.spine.qcfile): the qc stage's report and the store's take
selection read the same verdicts from it, and refuse the same bad files with the same line."""
from __future__ import annotations

import json
import shutil

import pytest

from odsplat.acquisition import QCReport, QCSettings, run_qc
from odsplat.spine.errors import InputError
from odsplat.spine.impulse import ImpactSettings
from odsplat.spine.qcfile import SCHEMA, QCFile, TakeQC
from odsplat.spine.store import Capture


@pytest.fixture()
def cap(sim_capture, tmp_path) -> Capture:
    """The simulated rig's capture (six takes: a double hit and a take with dropped frames among them, both redone),
    with its takes' recorded verdicts cleared, as an import leaves them."""
    dest = tmp_path / "cap"
    shutil.copytree(sim_capture.root, dest, ignore=shutil.ignore_patterns("derived"))
    c = Capture.open(dest)
    for t in c.manifest.takes:
        t.qc = "unchecked"
    c.save_manifest()
    return Capture.open(dest)


def test_the_report_and_the_store_read_the_same_verdicts(cap):
    assert cap.qc_verdicts() == {} and cap.select_takes("accepted") == []   # before the qc stage ran
    with pytest.raises(InputError, match="no QC result"):
        QCReport.read(cap)
    settings = QCSettings(force_band_n=(10.0, 1000.0), impacts=ImpactSettings(rebound_fraction=0.06))
    report = run_qc(cap, settings)
    checked = {t.name: t.checked for t in report.takes}
    assert len(checked) == 6 and sorted(checked.values()).count("rejected") == 2   # the double hit, the lost frames
    double = next(t for t in report.takes if "double_hit" in t.reasons)
    assert double.n_impacts == 2 and double.status == "rejected" and isinstance(double, TakeQC)
    again = QCReport.read(cap)
    assert again == report and again.settings.impacts.rebound_fraction == 0.06
    doc = QCFile.read(cap.paths.qc_json, cap.id)
    assert doc.takes == report.takes and doc.settings["impacts"]["rebound_fraction"] == 0.06
    assert cap.qc_verdicts() == doc.verdicts() == checked
    assert [t.name for t in cap.select_takes("accepted")] == [n for n, v in checked.items() if v == "accepted"]


def _refusals(cap: Capture, doc: dict) -> tuple[str, str]:
    cap.paths.qc_json.write_text(json.dumps(doc))
    with pytest.raises(InputError) as by_report:
        QCReport.read(cap)
    with pytest.raises(InputError) as by_store:
        cap.qc_verdicts()
    return str(by_report.value), str(by_store.value)


def test_both_readers_refuse_a_bad_file_with_the_same_line(cap):
    run_qc(cap)
    good = json.loads(cap.paths.qc_json.read_text())
    assert good["kind"] == "odsplat.qc" and good["schema_version"] == SCHEMA == 2
    assert good["provenance"]["settings"]["impacts"]["noise_sigmas"] == 10.0

    bad = json.loads(json.dumps(good))
    bad["takes"][1]["checked"] = "maybe"
    report, store = _refusals(cap, bad)
    assert report == store and "takes[1].checked" in report and "expected one of accepted, rejected" in report
    bad = json.loads(json.dumps(good))
    del bad["takes"][0]["name"]
    report, store = _refusals(cap, bad)
    assert report == store and "takes[0].name" in report and "required field is missing" in report
    report, store = _refusals(cap, {**good, "schema_version": 1})   # double_hit_fraction in its settings
    assert report == store and "schema 1 is older" in report
    report, store = _refusals(cap, {**good, "capture_id": "someone-elses"})
    assert report == store and "belongs to another capture" in report
    report, store = _refusals(cap, {**good, "takes": {"v00_000": "accepted"}})
    assert report == store and "takes: expected a list" in report
