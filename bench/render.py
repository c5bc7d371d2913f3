"""Benchmark of the hil_sim software renderer: frames/s of `render` against its 1-thread run and the numpy reference.

Prints one JSON line on stdout; progress goes to stderr. The scene is built by `synthetic_scene` (a bent, subdivided
textured column on a textured floor board) or, with --scene rig, the simulated rig's default scene (hil_sim.scene);
frames/s are after JIT warm-up (median frame time), each frame a slightly different deformation (as in a vibration
take), `supersample` 3. compile_s is the first call of a fresh process with an empty numba cache (a subprocess);
first_call_s the first call here.
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, NamedTuple

import numba
import numpy as np

from odsplat.hil_sim.render import PinholeCamera, TexturedMesh, lambert_shade, render, render_reference

log = logging.getLogger("bench.render")

REPO = Path(__file__).resolve().parents[1]
SUPERSAMPLE = 3
SIZES = (128, 256, 512)
TARGET_FPS_256 = 20.0
MIN_TIME_S = 1.0  # time at least this long (and at least 5 frames) per figure


class Scene(NamedTuple):
    """A mesh (at rest) and how to deform and view it; `frame(k)` gives the mesh of frame k."""

    mesh: TexturedMesh
    atlas: np.ndarray
    eye_m: tuple[float, float, float]
    target_m: tuple[float, float, float]
    fov_deg: float
    bend_m: np.ndarray  # (V, 3) displacement of the first mode shape, 1 m amplitude

    def frame(self, k: int) -> TexturedMesh:
        v = self.mesh.vertices_m + 0.01 * np.sin(0.7 * k) * self.bend_m  # up to 1 cm, a few px
        light = (-0.4, 1.0, -1.2)  # travelling away from a light above, left and in front of the camera
        return TexturedMesh(v, self.mesh.faces, self.mesh.uv_px, self.mesh.object_id,
                            lambert_shade(v, self.mesh.faces, light))

    def camera(self, size_px: int) -> PinholeCamera:
        return PinholeCamera.look_at(self.eye_m, self.target_m, fov_deg=self.fov_deg, width_px=size_px,
                                     height_px=size_px)


def _speckle(size: int, grain_px: float, rng: np.random.Generator) -> np.ndarray:
    """Smooth random speckle in [0.1, 0.9]: white noise low-passed by a Gaussian of `grain_px`."""
    f = np.fft.fftfreq(size)
    lowpass = np.exp(-2.0 * (np.pi * grain_px) ** 2 * (f[:, None] ** 2 + f[None, :] ** 2))
    img = np.fft.ifft2(np.fft.fft2(rng.standard_normal((size, size))) * lowpass).real
    return (0.5 + 0.4 * np.clip(img / (3 * img.std()), -1, 1)).astype(np.float32)


def _grid(origin, du, dv, nu: int, nv: int, uv0, uv_du, uv_dv) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A planar nu x nv grid of quads, two counter-clockwise triangles each around du x dv; its own vertices."""
    a, b = np.meshgrid(np.linspace(0, 1, nu + 1), np.linspace(0, 1, nv + 1))
    a, b = a.ravel()[:, None], b.ravel()[:, None]
    verts = np.asarray(origin) + a * np.asarray(du) + b * np.asarray(dv)
    uv = np.asarray(uv0) + a * np.asarray(uv_du) + b * np.asarray(uv_dv)
    i, j = np.meshgrid(np.arange(nu), np.arange(nv))
    q = (j * (nu + 1) + i).ravel()
    quads = np.stack([q, q + 1, q + nu + 2, q + nu + 1], axis=1)
    faces = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    return verts, faces, uv


def synthetic_scene(n_triangles: int = 10_000, *, seed: int = 0) -> Scene:
    """A 0.3 x 0.3 x 1 m column (object 1, ~90 % of the triangles, bending in x) on a 1.6 m floor board (object 2)."""
    rng = np.random.default_rng(seed)
    atlas = _speckle(512, 1.5, rng)
    h, height = 0.15, 1.0
    nu = max(1, int(round(np.sqrt(0.9 * n_triangles / 26))))  # 4 sides of nu x 3nu quads and a top of nu x nu
    nv = 3 * nu
    nf = max(1, int(round(np.sqrt(0.1 * n_triangles / 2))))
    up = (0, 0, height)
    groups = [  # (origin, du, dv) with du x dv pointing outwards, atlas region
        ((h, -h, 0), (0, 2 * h, 0), up, (0, 0), (127, 0), (0, 380)),
        ((h, h, 0), (-2 * h, 0, 0), up, (128, 0), (127, 0), (0, 380)),
        ((-h, h, 0), (0, -2 * h, 0), up, (256, 0), (127, 0), (0, 380)),
        ((-h, -h, 0), (2 * h, 0, 0), up, (384, 0), (127, 0), (0, 380)),
        ((-h, -h, height), (2 * h, 0, 0), (0, 2 * h, 0), (0, 384), (127, 0), (0, 127)),
    ]
    verts, faces, uvs, ids = [], [], [], []
    n = 0
    floor = ((-0.8, -0.8, 0), (1.6, 0, 0), (0, 1.6, 0), (0, 0), (511, 0), (0, 511))
    for k, (origin, du, dv, uv0, uv_du, uv_dv) in enumerate(groups + [floor]):
        nu_k, nv_k = (nf, nf) if k == 5 else (nu, nu if k == 4 else nv)
        v, f, uv = _grid(origin, du, dv, nu_k, nv_k, uv0, uv_du, uv_dv)
        verts.append(v), faces.append(f + n), uvs.append(uv), ids.append(np.full(len(f), 2 if k == 5 else 1))
        n += len(v)
    verts = np.concatenate(verts)
    ids = np.concatenate(ids)
    # First bending mode of a cantilever, roughly: x displacement growing with height squared, column only.
    bend = np.zeros_like(verts)
    on_column = np.zeros(len(verts), bool)
    on_column[np.concatenate(faces)[ids == 1].ravel()] = True
    bend[on_column, 0] = (verts[on_column, 2] / height) ** 2
    mesh = TexturedMesh(verts, np.concatenate(faces), np.concatenate(uvs), ids.astype(np.int16))
    return Scene(mesh, atlas, (1.3, -1.9, 1.1), (0.0, 0.0, 0.42), 38.0, bend)


def rig_scene(n_triangles: int | None = None) -> Scene:
    """The hil_sim rig's default scene (its own triangle count), bent in its first mode, seen as a take sees it."""
    from odsplat.hil_sim.scene import build_scene

    rig = build_scene()
    mesh = rig.mesh()
    bend = rig.shapes[:, 0, :]
    bend = bend / np.abs(bend).max()
    return Scene(mesh, rig.atlas, (1.1, -1.3, 1.0), (0.15, 0.0, 0.33), 42.0, bend)


SCENES = {"synthetic": synthetic_scene, "rig": rig_scene}


def _fps(scene: Scene, size: int, *, reference: bool = False) -> tuple[float, int, dict[str, float]]:
    """Frames/s at size x size, from the median frame time over at least MIN_TIME_S (one frame for the reference),
    and the scene's coverage. Each frame deforms the mesh, shades it (lambert_shade) and renders it, as a take would.
    The median, not the mean, so that other processes on a shared machine skew it less."""
    cam = scene.camera(size)
    fn = render_reference if reference else render
    times = []
    t_end = time.perf_counter() + MIN_TIME_S
    while not times or not reference and (len(times) < 5 or time.perf_counter() < t_end):
        t0 = time.perf_counter()
        res = fn(scene.frame(len(times)), cam, scene.atlas, supersample=SUPERSAMPLE)
        times.append(time.perf_counter() - t0)
    cover = {"coverage": float(res.coverage.mean()), "structure_coverage": float((res.object_id == 1).mean())}
    return 1.0 / float(np.median(times)), len(times), cover


def _cold_compile_s() -> float:
    """Seconds for import + the first render of a fresh process whose numba cache is empty."""
    code = ("import time; t0 = time.perf_counter(); import numpy as np; "
            "from odsplat.hil_sim.render import PinholeCamera, TexturedMesh, render; "
            "cam = PinholeCamera.look_at((0, -2, 0), (0, 0, 0), fov_deg=40, width_px=32, height_px=32); "
            "m = TexturedMesh(np.eye(3), [[0, 1, 2]], np.zeros((3, 2)), [1]); "
            "render(m, cam, np.ones((4, 4), np.float32)); print(time.perf_counter() - t0)")
    with tempfile.TemporaryDirectory(prefix="odsplat-numba-") as cache:
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, timeout=300,
                             env={**os.environ, "NUMBA_CACHE_DIR": cache})
    if out.returncode != 0:
        raise RuntimeError(f"cold compile run failed: {out.stderr}")
    return float(out.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", choices=sorted(SCENES), default="synthetic",
                        help="scene to render (default synthetic)")
    parser.add_argument("--triangles", type=int, default=10_000,
                        help="approximate triangle count of the synthetic scene")
    parser.add_argument("--sizes", type=int, nargs="+", default=list(SIZES), help="square image sizes in px")
    parser.add_argument("--no-reference", action="store_true", help="skip the slow numpy reference baseline")
    parser.add_argument("--no-cold-compile", action="store_true",
                        help="skip timing a compile with an empty numba cache")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, stream=sys.stderr, format="%(name)s: %(message)s")

    scene = SCENES[args.scene](args.triangles)
    n_tri = len(scene.mesh.faces)
    log.info("scene %s: %d triangles, %d vertices", args.scene, n_tri, len(scene.mesh.vertices_m))
    compile_s = None
    if not args.no_cold_compile:
        log.info("cold compile (fresh process, empty numba cache)")
        compile_s = _cold_compile_s()
    t0 = time.perf_counter()
    render(scene.frame(0), scene.camera(args.sizes[0]), scene.atlas, supersample=SUPERSAMPLE)
    first_call_s = time.perf_counter() - t0

    threads = numba.get_num_threads()
    result: dict[str, Any] = {
        "bench": "render", "scene": args.scene, "triangles": n_tri, "supersample": SUPERSAMPLE,
        "sizes": args.sizes, "threads": threads, "cpu_count": os.cpu_count(),
        "baseline": "render_reference: numpy per-face Moller-Trumbore ray caster over each face's bounding box",
        "baseline_1thread": "render with numba.set_num_threads(1)",
        "compile_s": None if compile_s is None else round(compile_s, 2), "first_call_s": round(first_call_s, 2),
    }
    for size in args.sizes:
        fps, frames, cover = _fps(scene, size)
        log.info("%dx%d: %.1f frames/s (%d frames), coverage %.2f (structure %.2f)", size, size, fps, frames,
                 cover["coverage"], cover["structure_coverage"])
        numba.set_num_threads(1)
        try:
            fps1, _, _ = _fps(scene, size)
        finally:
            numba.set_num_threads(threads)
        log.info("%dx%d, 1 thread: %.1f frames/s", size, size, fps1)
        entry = {"fps": round(fps, 2), "fps_1thread": round(fps1, 2), "ratio_vs_1thread": round(fps / fps1, 2),
                 "coverage": round(cover["coverage"], 3), "structure_coverage": round(cover["structure_coverage"], 3)}
        if not args.no_reference:
            fps_ref, _, _ = _fps(scene, size, reference=True)
            log.info("%dx%d, numpy reference: %.3f frames/s", size, size, fps_ref)
            entry.update(baseline_fps=round(fps_ref, 4), ratio=round(fps / fps_ref, 1))
        result[str(size)] = entry
    if "256" in result:
        result["target_fps_256"] = TARGET_FPS_256
        result["meets_target_256"] = result["256"]["fps"] >= TARGET_FPS_256
    print(json.dumps(result), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
