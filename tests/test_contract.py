"""How derived files describe themselves (odsplat.spine.contract) and the registry of their paths (Capture.paths)."""
from __future__ import annotations

import pytest

from odsplat.spine.contract import check, describe, digest
from odsplat.spine.errors import InputError
from odsplat.spine.manifest import Manifest
from odsplat.spine.store import Capture
from odsplat.sync import SyncSettings


def test_a_header_round_trips_and_its_fingerprint_follows_settings_and_inputs():
    prov = describe("cap-1", "odsplat.sync", 2, SyncSettings(), {"takes": "abc"})
    back = check(prov.header(), "sync.json", kind="odsplat.sync", schema_version=2, capture_id="cap-1")
    assert back.settings == prov.settings and back.inputs == {"takes": "abc"} and back.run_id == prov.run_id
    assert back.fingerprint == prov.fingerprint
    again = describe("cap-1", "odsplat.sync", 2, SyncSettings(), {"takes": "abc"})
    assert again.fingerprint == prov.fingerprint and again.run_id != prov.run_id   # a new run, the same result
    assert describe("cap-1", "odsplat.sync", 2, SyncSettings(method="ttl"), {"takes": "abc"}).fingerprint != \
        prov.fingerprint
    assert describe("cap-1", "odsplat.sync", 2, SyncSettings(), {"takes": "abd"}).fingerprint != prov.fingerprint
    assert digest({"b": 1, "a": (1, 2)}) == digest({"a": [1, 2], "b": 1})


@pytest.mark.parametrize("doc, message", [
    ({"kind": "odsplat.poses", "schema_version": 2, "capture_id": "cap-1"}, "not an odsplat.sync file"),
    ({"format": "odsplat-sync", "version": 1}, "written by an older odsplat"),
    ({"kind": "odsplat.sync", "schema_version": "1.0", "capture_id": "cap-1"}, "schema '1.0' is older"),
    ({"kind": "odsplat.sync", "schema_version": 1, "capture_id": "cap-1"}, "schema 1 is older"),
    ({"kind": "odsplat.sync", "schema_version": 3, "capture_id": "cap-1"}, "schema 3 is newer than this odsplat"),
    ({"kind": "odsplat.sync", "schema_version": 2, "capture_id": "cap-2"}, "belongs to another capture"),
    ({"kind": "odsplat.sync", "schema_version": True, "capture_id": "cap-1"}, "expected an integer"),
    ([1, 2], "expected a JSON object"),
])
def test_foreign_older_and_newer_files_are_refused_naming_the_file(doc, message):
    with pytest.raises(InputError, match=message) as err:
        check(doc, "derived/sync.json", kind="odsplat.sync", schema_version=2, capture_id="cap-1")
    assert err.value.source == "derived/sync.json"


def test_the_paths_registry_creates_nothing_and_can_point_elsewhere(tmp_path):
    cap = Capture(tmp_path / "cap", Manifest(name="cap"))
    assert cap.paths.sync_json == tmp_path / "cap" / "derived" / "sync.json"
    assert cap.paths.frames("magnified/phase", "v00") == tmp_path / "cap" / "derived" / "magnified" / "phase" / "v00.h5"
    assert cap.paths.frames("sync", "v00") == cap.paths.aligned("v00")
    assert cap.derived_dir == cap.paths.root and not (tmp_path / "cap").exists()   # reading it made nothing
    other = Capture(tmp_path / "cap", Manifest(name="cap"), derived=tmp_path / "scratch")
    assert other.paths.stamp("sync") == tmp_path / "scratch" / "pipeline" / "sync.json"
    # A capture's id is its manifest's (set when it is created), else a hash of its name and creation time.
    assert Capture(tmp_path, Manifest(name="x", capture_id="abc")).id == "abc"
    m = Manifest(name="x")
    assert Capture(tmp_path, m).id == Capture(tmp_path / "copy", m).id != Capture(tmp_path, Manifest(name="y")).id
