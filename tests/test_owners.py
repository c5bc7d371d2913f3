"""Each file odsplat writes has one owner, the only code that reads it (docs/architecture.md, "The rule between
stages"). This walks the syntax of every module of the package, the bench and the tools:

- a call that reads a file's contents (`json.load(s)`, `np.load`, `h5py.File`, `plyfile.PlyData.read`, and our own
  checked readers `load_json` and `read_npz`) may stand only in the modules listed in READERS, each with what it
  reads;
- such a call whose arguments name a derived file through `Capture.paths` (`capture.paths.sync_json`, ...) may
  stand only in that file's owner (OWNERS).

A new reader anywhere else fails here until it is either moved into the owner or listed, with its reason."""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
FOLDERS = ("odsplat", "acquisition", "sync", "processing", "reconstruction", "analysis", "hil_sim", "bench", "tools")
READ_CALLS = {"json.load", "json.loads", "np.load", "numpy.load", "h5py.File", "PlyData.read", "plyfile.PlyData.read",
              "load_json", "read_npz"}

# The derived files by their name in odsplat.spine.paths.DerivedPaths, and the one module that reads each.
OWNERS = {
    "qc_json": "odsplat/spine/qcfile.py",
    "sync_json": "sync/align.py",
    "magnify_json": "processing/magnify.py",
    "poses_json": "reconstruction/pose_result.py",
    "points_npz": "reconstruction/pose_result.py",
    "reconstruction_json": "reconstruction/model.py",
    "trajectories_npz": "reconstruction/model.py",
    "measured_motion_npz": "reconstruction/model.py",
    "gaussians_ply": "reconstruction/gaussians.py",
    "analysis_json": "analysis/document.py",
    "video2d_json": "analysis/video2d.py",
    "video2d_npz": "analysis/video2d.py",
    "stamp": "odsplat/app/pipeline.py",
    "lock": "odsplat/spine/lock.py",
}
# Every module that reads a file's contents, and what it reads.
READERS = {
    "odsplat/spine/manifest.py": "load_json: the one checked JSON reader (capture.json, rig files, every index)",
    "odsplat/spine/contract.py": "read_npz: the one checked reader of a derived .npz",
    "odsplat/spine/framefile.py": "the derived frame files (magnified/): one layout, one reader",
    "odsplat/spine/take_reader.py": "the raw takes (takes/*.h5) and their JSON attributes",
    "odsplat/spine/take_writer.py": "the take being written (SWMR)",
    "odsplat/spine/recovery.py": "a crashed take's .partial file",
    "odsplat/spine/integrity.py": "`odsplat verify`: every raw take read whole",
    "odsplat/spine/space.py": "opens every HDF5 file written, beside its disk reserve",
    "odsplat/spine/lock.py": "the lock file's holder",
    "odsplat/spine/qcfile.py": "derived/qc.json",
    "sync/align.py": "derived/sync.json",
    "sync/aligned.py": "derived/sync/NAME.h5: how each take is aligned (its frames are computed from the raw take)",
    "processing/magnify.py": "derived/magnified/METHOD/magnify.json; parses --option values (no file)",
    "reconstruction/pose_result.py": "derived/poses.json and points.npz",
    "reconstruction/model.py": "derived/reconstruction/: its index and the motion .npz files",
    "reconstruction/known_poses.py": "a file of known cameras the engineer gives (PoseSettings.from_file)",
    "reconstruction/gaussians.py": "the Gaussians' .ply",
    "analysis/document.py": "derived/analysis/analysis.json",
    "analysis/results_h5.py": "derived/analysis/results.h5 (its JSON attributes)",
    "analysis/shape3d.py": "derived/analysis/plots/shapes3d.json (the report's 3D shapes)",
    "odsplat/app/pipeline.py": "the stamps in derived/pipeline/",
    "bench/store.py": "its baseline: the same frames as one .npy, read whole",
    "bench/sensitivity.py": "derived/poses.json, to move every camera by a rounding error before a rerun",
    "hil_sim/rig.py": "the simulated rig's ground truth (.npz), written beside the capture or video by hil_sim",
    "analysis/video2d.py": "derived/analysis/video2d.json and video2d.npz (the 2D path's results)",
    "bench/oma.py": "LADISK's video displacements (../shared/data, .npy), the bench's real input",
}


def _modules() -> list[Path]:
    return [p for folder in FOLDERS for p in sorted((REPO / folder).rglob("*.py"))]


def _dotted(node: ast.expr) -> str:
    try:
        return ast.unparse(node)
    except Exception:   # noqa: BLE001 (a node unparse cannot render is no reader)
        return ""


def _derived_names(call: ast.Call) -> set[str]:
    """The DerivedPaths names the call's arguments mention: `X.paths.NAME` or `X.paths.NAME(...)`."""
    names = set()
    for arg in [*call.args, *(k.value for k in call.keywords)]:
        for node in ast.walk(arg):
            if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Attribute) and node.value.attr == "paths":
                names.add(node.attr)
    return names


def reads(source: str) -> list[tuple[int, str, set[str]]]:
    """(line, the reader called, the derived files its arguments name) for every reading call in `source`."""
    out = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Call):
            name = _dotted(node.func)
            if name in READ_CALLS or name.endswith(".read_npz") or name.endswith(".load_json"):
                out.append((node.lineno, name, _derived_names(node)))
    return out


def violations(rel: str, source: str) -> list[str]:
    found = []
    for line, name, derived in reads(source):
        if rel not in READERS:
            found.append(f"{rel}:{line}: {name} outside the modules that read files (READERS)")
        for d in sorted(derived):
            if OWNERS.get(d) != rel:
                found.append(f"{rel}:{line}: {name} of paths.{d}, whose owner is {OWNERS.get(d, 'not listed')}")
    return found


def test_every_file_is_read_only_by_its_owner():
    problems = [v for p in _modules() for v in violations(p.relative_to(REPO).as_posix(), p.read_text())]
    assert not problems, "\n".join(problems)


def test_the_lists_name_modules_that_exist_and_read():
    for rel in {*READERS, *OWNERS.values()}:
        path = REPO / rel
        assert path.is_file(), rel
        assert reads(path.read_text()), f"{rel} is listed as a reader but reads nothing"


# Reads a careless change might add, each outside the file's owner: the walk must find every one.
OUTSIDE = {
    "analysis/report.py": "import json\ndoc = json.loads(cap.paths.analysis_json.read_text())\n",
    "bench/sync.py": "import numpy as np\nz = np.load(capture.paths.trajectories_npz)\n",
    "sync/align.py": "from odsplat.spine.manifest import load_json\nq = load_json(capture.paths.qc_json)\n",
    "odsplat/app/viewer/model.py": "import h5py\nf = h5py.File(path)\n",
}


@pytest.mark.parametrize("rel", OUTSIDE)
def test_a_read_outside_the_owner_is_found(rel):
    assert violations(rel, OUTSIDE[rel])
