"""hil_sim.render against its numpy ray-caster reference, the pixel/camera conventions, sub-pixel sensitivity,
depth/id/coverage maps, near-plane clipping and the sensor model."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from odsplat.hil_sim.render import PinholeCamera, TexturedMesh, expose, lambert_shade, render, render_reference, to_mono
from odsplat.spine.errors import InputError

REPO = Path(__file__).resolve().parents[2]


def _frontal(width: int, height: int, f: float, cx: float | None = None, cy: float | None = None) -> PinholeCamera:
    """Camera at the world origin looking down +z (world axes = camera axes)."""
    cx = (width - 1) / 2 if cx is None else cx
    cy = (height - 1) / 2 if cy is None else cy
    return PinholeCamera(np.array([[f, 0, cx], [0, f, cy], [0, 0, 1.0]]), np.eye(3), np.zeros(3), width, height)


def _unproject(cam: PinholeCamera, px, depth) -> np.ndarray:
    """World points at image positions px (N, 2) and camera depths (N,)."""
    px = np.atleast_2d(np.asarray(px, dtype=float))
    ray = np.c_[px, np.ones(len(px))] @ np.linalg.inv(cam.K).T
    return (ray * np.asarray(depth, dtype=float).reshape(-1, 1) - cam.t) @ cam.R


def _quads(corners: list[np.ndarray], uvs: list[np.ndarray], ids: list[int]) -> TexturedMesh:
    """Quads (4 corners each, in order) as two triangles apiece; every quad has its own vertices."""
    faces = [np.array([[0, 1, 2], [0, 2, 3]]) + 4 * k for k in range(len(corners))]
    return TexturedMesh(np.concatenate(corners), np.concatenate(faces), np.concatenate(uvs), np.repeat(ids, 2))


def _speckle(size: int, grain_px: float, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    f = np.fft.fftfreq(size)
    lowpass = np.exp(-2.0 * (np.pi * grain_px) ** 2 * (f[:, None] ** 2 + f[None, :] ** 2))
    img = np.fft.ifft2(np.fft.fft2(rng.standard_normal((size, size))) * lowpass).real
    return (0.5 + 0.4 * np.clip(img / (3 * img.std()), -1, 1)).astype(np.float32)


def _assert_same(res, ref, tol: float = 1e-5) -> None:
    np.testing.assert_allclose(res.image, ref.image, atol=tol, rtol=0)
    np.testing.assert_allclose(res.coverage, ref.coverage, atol=1e-6, rtol=0)
    np.testing.assert_array_equal(res.object_id, ref.object_id)
    np.testing.assert_array_equal(np.isinf(res.depth_m), np.isinf(ref.depth_m))
    hit = np.isfinite(ref.depth_m)
    np.testing.assert_allclose(res.depth_m[hit], ref.depth_m[hit], rtol=1e-6)


def _overlap_scene(rgb: bool):
    """Three textured triangles at different depths on a 24 x 20 image, one crossing the near plane z = 0.8."""
    cam = _frontal(24, 20, 30.0)
    tri_px = [[(-3.2, -2.1), (26.3, 3.7), (4.9, 23.4)], [(8.3, 2.6), (20.1, 9.3), (10.7, 17.8)],
              [(2.2, 16.6), (13.9, 5.1), (30.4, 21.3)]]
    depths = [(3.1, 2.2, 2.6), (1.7, 1.4, 1.9), (0.5, 1.3, 2.4)]  # the last vertex of face 3 lies behind z = 0.8
    verts = np.concatenate([_unproject(cam, p, d) for p, d in zip(tri_px, depths)])
    rng = np.random.default_rng(3)
    uv = rng.uniform(-1, 17, (9, 2))  # some texel coordinates off the atlas: clamped to its edge
    atlas = rng.uniform(0, 1, (16, 16, 3) if rgb else (16, 16)).astype(np.float32)
    mesh = TexturedMesh(verts, np.arange(9).reshape(3, 3), uv, [1, 2, 3], shade=[1.0, 0.8, 0.6])
    return mesh, cam, atlas


@pytest.mark.parametrize("supersample", [3, 2, 1])
@pytest.mark.parametrize("rgb", [False, True])
def test_render_matches_ray_caster_reference(supersample, rgb):
    mesh, cam, atlas = _overlap_scene(rgb)
    bg = np.array([0.1, 0.2, 0.3]) if rgb else 0.25
    res = render(mesh, cam, atlas, supersample=supersample, background=bg, near_m=0.8)
    ref = render_reference(mesh, cam, atlas, supersample=supersample, background=bg, near_m=0.8)
    assert res.image.shape == ((20, 24, 3) if rgb else (20, 24)) and res.image.dtype == np.float32
    assert set(np.unique(res.object_id)) == {0, 1, 2, 3}  # all faces and background visible, face 2 over face 1
    if supersample > 1:
        assert ((res.coverage > 0) & (res.coverage < 1)).sum() > 20  # anti-aliased edges present
    _assert_same(res, ref)
    assert np.nanmin(np.where(np.isfinite(res.depth_m), res.depth_m, np.nan)) >= 0.8 - 1e-6


def test_camera_convention_x_right_y_down_z_forward():
    eye, target = np.array([2.0, -3.0, 1.5]), np.array([0.0, 0.0, 0.5])
    cam = PinholeCamera.look_at(eye, target, fov_deg=50, width_px=64, height_px=48)
    np.testing.assert_allclose(cam.center_m, eye, atol=1e-12)
    np.testing.assert_allclose(cam.R @ cam.R.T, np.eye(3), atol=1e-12)
    assert cam.K[0, 0] == pytest.approx(32 / np.tan(np.radians(25)))
    px, depth = cam.project(target)
    np.testing.assert_allclose(px[0], [31.5, 23.5], atol=1e-9)  # the principal point is the image centre
    assert depth[0] == pytest.approx(np.linalg.norm(target - eye))
    right = np.cross(target - eye, (0, 0, 1))
    right /= np.linalg.norm(right)
    (xr, yr), (xd, yd) = cam.project([target + 0.1 * right, target - [0, 0, 0.1]])[0]
    assert xr > 31.5 + 1 and abs(yr - 23.5) < 1e-9  # to the camera's right: larger x
    assert yd > 23.5 + 1  # below (world z down): larger y
    assert np.isnan(cam.project(eye - (target - eye))[0]).all()  # behind the camera


def test_textured_blob_lands_at_its_projection():
    """A Gaussian blob painted at the texture's centre texel, on a fronto-parallel square centred at a point, has
    its rendered intensity centroid at camera.project(point): pixel centres and texel centres are at integers."""
    cam = PinholeCamera.look_at((2.0, -3.0, 1.5), (0.0, 0.0, 0.5), fov_deg=50, width_px=64, height_px=48)
    n = 33
    g = np.exp(-0.5 * ((np.arange(n) - (n - 1) / 2) / 4.0) ** 2)
    atlas = np.outer(g, g).astype(np.float32)  # peak at texel (16, 16), the atlas centre
    for point in ([0.37, 0.21, 0.83], [-0.29, -0.12, 0.31]):
        point = np.asarray(point)
        r0, r1 = cam.R[0] * 0.4, cam.R[1] * 0.4  # camera right and down: the square is fronto-parallel
        corners = np.array([point - r0 - r1, point + r0 - r1, point + r0 + r1, point - r0 + r1])
        uv = np.array([[-0.5, -0.5], [n - 0.5, -0.5], [n - 0.5, n - 0.5], [-0.5, n - 0.5]])
        res = render(_quads([corners], [uv], [1]), cam, atlas, supersample=3)
        ys, xs = np.mgrid[:48, :64]
        centroid = np.array([(res.image * xs).sum(), (res.image * ys).sum()]) / res.image.sum()
        expected = cam.project(point)[0][0]
        np.testing.assert_allclose(centroid, expected, atol=0.02)
        assert abs(centroid[0] - 31.5) > 2 and abs(centroid[1] - 23.5) > 2  # a generic spot, off the centre


def _shifted_plane(shift_px: float, supersample: int = 3):
    """A speckled plane filling a 64 x 64 view at 2 m, texels about 1 px, moved right by shift_px in the image."""
    cam = _frontal(64, 64, 100.0)
    z, size = 2.0, 128
    half = size / 2 * z / cam.K[0, 0]
    dx = shift_px * z / cam.K[0, 0]
    corners = np.array([[-half + dx, -half, z], [half + dx, -half, z], [half + dx, half, z], [-half + dx, half, z]])
    uv = np.array([[-0.5, -0.5], [size - 0.5, -0.5], [size - 0.5, size - 0.5], [-0.5, size - 0.5]])
    return render(_quads([corners], [uv], [1]), cam, _speckle(size, 1.5), supersample=supersample).image


def test_subpixel_motion_changes_pixels_linearly_and_is_recoverable():
    i0, i1, i2 = (_shifted_plane(d) for d in (0.0, 0.01, 0.02))
    d1, d2 = np.abs(i1 - i0).mean(), np.abs(i2 - i0).mean()
    assert d1 > 1e3 * np.finfo(np.float32).eps * i0.mean()  # far above float32 rounding
    assert d2 / d1 == pytest.approx(2.0, rel=0.1)
    # Optical-flow identity: I1(x) = I0(x - d), so I1 - I0 = -d dI/dx (five-point derivative: 2 % bias, not 6 %).
    ix = (i0[2:-2, :-4] - 8 * i0[2:-2, 1:-3] + 8 * i0[2:-2, 3:-1] - i0[2:-2, 4:]) / 12
    di = (i1 - i0)[2:-2, 2:-2]
    assert -(di * ix).sum() / (ix**2).sum() == pytest.approx(0.01, rel=0.1)
    # After a noiseless 12-bit exposure the shift is still visible in many pixels.
    q0, q1 = (expose(i, bit_depth=12, shot_noise=False, read_noise_e=0.0) for i in (i0, i1))
    assert np.mean(q0 != q1) > 0.2


def test_depth_id_and_coverage_of_planes():
    cam = _frontal(40, 30, 50.0)
    s = 3
    # A fronto-parallel rectangle at 2.5 m spanning x in [10.37, 25.81], y in [5.62, 20.13] px.
    x0, x1, y0, y1 = 10.37, 25.81, 5.62, 20.13
    rect = _unproject(cam, [(x0, y0), (x1, y0), (x1, y1), (x0, y1)], [2.5] * 4)
    res = render(_quads([rect], [np.zeros((4, 2))], [7]), cam, np.ones((2, 2), np.float32), supersample=s)
    c = np.arange(40), np.arange(30)
    inside = (c[1][:, None] > y0) & (c[1][:, None] < y1) & (c[0] > x0) & (c[0] < x1)  # pixel centres
    np.testing.assert_array_equal(res.object_id, np.where(inside, 7, 0))
    np.testing.assert_allclose(res.depth_m[inside], 2.5, rtol=1e-7)
    assert np.isinf(res.depth_m[~inside]).all()
    # Exact area of each pixel [i-0.5, i+0.5] inside the rectangle: product of 1D overlaps.
    fx = np.clip(np.minimum(c[0] + 0.5, x1) - np.maximum(c[0] - 0.5, x0), 0, 1)
    fy = np.clip(np.minimum(c[1] + 0.5, y1) - np.maximum(c[1] - 0.5, y0), 0, 1)
    area = fy[:, None] * fx
    assert (res.coverage[area == 1] == 1).all() and (res.coverage[area == 0] == 0).all()
    edge = (area > 0) & (area < 1) & (fx[None, :] == 1) | (fy[:, None] == 1) & (area > 0) & (area < 1)
    assert edge.sum() > 40
    assert np.abs(res.coverage - area)[edge].max() <= 1 / (2 * s) + 1e-6  # one straight edge: half a sample row
    np.testing.assert_allclose(res.image, res.coverage, atol=1e-6)  # white texture on black: image = coverage

    # A plane tilted about the camera y axis, z = 2 + 0.5 X, through the whole view; one slanted edge crosses it.
    g, z0 = 0.5, 2.0
    zs = lambda px: z0 / (1 - g * (px[0] - cam.K[0, 2]) / cam.K[0, 0])  # noqa: E731  depth of the ray through px
    corners_px = [(-5.0, -40.0), (60.0, -40.0), (60.0, 60.0), (-5.0, 60.0)]
    tilted = _unproject(cam, corners_px, [zs(p) for p in corners_px])
    # A slanted left edge from (31.3, -40) to (-5, 60).
    tilted[0] = _unproject(cam, [(31.3, -40.0)], [zs((31.3, -40.0))])[0]
    res = render(_quads([tilted], [np.zeros((4, 2))], [2]), cam, np.ones((2, 2), np.float32), supersample=s)
    ys, xs = np.mgrid[:30, :40].astype(float)
    hit = res.object_id == 2
    assert 0.3 < hit.mean() < 0.9
    np.testing.assert_allclose(res.depth_m[hit], z0 / (1 - g * (xs[hit] - cam.K[0, 2]) / cam.K[0, 0]), rtol=1e-6)
    # Exact pixel areas right of the line through (31.3, -40) and (-5, 60): x_edge(y) is linear, so integrate it.
    x_at = lambda y: 31.3 + (y + 40.0) * (-36.3 / 100.0)  # noqa: E731
    fine = np.linspace(-0.5, 0.5, 401)[:, None]  # x_edge varies linearly: the midpoint rule on 400 rows is exact
    x_edge = x_at(ys[None] + (fine[:-1, :, None] + fine[1:, :, None]) / 2)
    frac = np.clip(xs[None] + 0.5 - np.maximum(x_edge, xs[None] - 0.5), 0, 1).mean(0)
    err = np.abs(res.coverage - frac)[(frac > 0) & (frac < 1)]
    assert err.size > 20 and err.max() <= 1 / (2 * s) + 1e-6 and err.mean() <= 1 / s**2


def test_shared_edges_through_samples_leave_no_cracks():
    """A grid of triangles whose vertices and edges pass exactly through sample positions covers every sample once."""
    cam = _frontal(20, 20, 40.0)
    n = 8
    gx, gy = np.meshgrid(np.arange(n + 1) * 2.0 + 2, np.arange(n + 1) * 2.0 + 2)  # vertices on pixel centres
    verts = _unproject(cam, np.c_[gx.ravel(), gy.ravel()], np.full(gx.size, 3.0))
    q = (np.arange(n)[:, None] * (n + 1) + np.arange(n)).ravel()
    faces = np.concatenate([np.c_[q, q + 1, q + n + 2], np.c_[q, q + n + 2, q + n + 1]])
    mesh = TexturedMesh(verts, faces, np.zeros((len(verts), 2)), np.ones(len(faces)))
    for s in (1, 3):
        res = render(mesh, cam, np.ones((1, 1), np.float32), supersample=s)
        assert (res.coverage[3:18, 3:18] == 1).all(), s  # interior: no gaps along shared edges


def test_near_plane_crossing_triangles_are_clipped_not_garbage():
    cam = PinholeCamera.look_at((0.0, 0.0, 1.0), (0.0, 5.0, 0.8), fov_deg=70, width_px=32, height_px=24)
    # A floor reaching far behind the camera, a face wholly behind it and one whose vertex sits on the eye plane.
    floor = np.array([[-50, -50, 0], [50, -50, 0], [50, 50, 0], [-50, 50, 0.0]])
    behind = np.array([[-1, -3, 1], [1, -3, 1], [0, -3, 2.0]])
    grazing = np.array([[0.3, 0.0, 1.2], [0.6, 4.0, 1.0], [-0.5, 4.0, 1.4]])
    verts = np.concatenate([floor, behind, grazing])
    faces = [[0, 1, 2], [0, 2, 3], [4, 5, 6], [7, 8, 9]]
    uv = np.random.default_rng(1).uniform(0, 8, (10, 2))
    mesh = TexturedMesh(verts, faces, uv, [2, 2, 5, 3])
    atlas = _speckle(8, 1.0)
    for near in (1e-3, 0.5):
        res = render(mesh, cam, atlas, near_m=near)
        assert np.isfinite(res.image).all() and np.isfinite(res.coverage).all()
        assert (res.object_id[-1] == 2).all() and (res.coverage[-1] == 1).all()  # floor below the horizon
        assert (res.object_id[:6] != 2).all()  # none above it
        assert 5 not in res.object_id and 3 in res.object_id
        assert res.depth_m[np.isfinite(res.depth_m)].min() >= near * (1 - 1e-6)
        _assert_same(res, render_reference(mesh, cam, atlas, near_m=near))


def test_backface_culling_and_lambert_shade():
    cam = _frontal(16, 16, 20.0)
    px = np.array([(1.9, 2.3), (2.4, 13.6), (13.2, 1.7)])  # counter-clockwise seen from the camera
    (ax, ay), (bx, by) = px[1] - px[0], px[2] - px[0]
    area = 0.5 * abs(ax * by - ay * bx)
    front = _unproject(cam, px, [2.0] * 3)
    # light_dir is the direction of travel: a light at the camera shines along +z onto the face turned towards it.
    assert lambert_shade(front, [[0, 1, 2]], light_dir=(0, 0, 1))[0] == pytest.approx(1.0, abs=0.01)
    np.testing.assert_allclose(lambert_shade(front, [[0, 1, 2], [0, 2, 1]], (0, 0, 1), ambient=0.2), [1.0, 0.2],
                               atol=0.01)
    flat = np.array([[0, 0, 2.0], [0, 1, 2], [1, 0, 2]])  # normal -z
    np.testing.assert_allclose(lambert_shade(flat, [[0, 1, 2]], (-1, 0, 1), ambient=0.2), 0.2 + 0.8 / np.sqrt(2),
                               rtol=1e-6)
    floor = np.array([[0, 0, 0.0], [1, 0, 0], [0, 1, 0]])  # counter-clockwise seen from above: normal +z
    assert lambert_shade(floor, [[0, 1, 2]], (0, 0, -1), ambient=0.3)[0] == pytest.approx(1.0)  # light overhead
    atlas = np.ones((1, 1), np.float32)
    for faces, culled in (([[0, 1, 2]], False), ([[0, 2, 1]], True)):
        mesh = TexturedMesh(front, faces, np.zeros((3, 2)), [1])
        covered = render(mesh, cam, atlas, cull_backfaces=True).coverage.sum()
        assert covered == (0 if culled else pytest.approx(area, rel=0.03))
        assert render(mesh, cam, atlas).coverage.sum() == pytest.approx(area, rel=0.03)


def test_expose_shot_and_read_noise_statistics():
    flat = np.full((256, 256), 0.5)
    rng = np.random.default_rng(0)
    # gain 1 DN/e: Poisson electrons give variance = mean (+1/12 from rounding).
    dn = expose(flat, bit_depth=12, full_well_e=4000, read_noise_e=0.0, gain_dn_per_e=1.0, rng=rng).astype(float)
    assert dn.mean() == pytest.approx(2000, abs=1.0)  # standard error 0.17
    assert dn.var() == pytest.approx(2000 + 1 / 12, rel=0.03)  # standard error 0.55 %
    dn = expose(flat, bit_depth=12, full_well_e=4000, read_noise_e=10.0, gain_dn_per_e=0.5, rng=rng).astype(float)
    assert dn.mean() == pytest.approx(1000, abs=0.5)
    assert dn.var() == pytest.approx(0.25 * (2000 + 100) + 1 / 12, rel=0.03)
    # Saturation: the well clips at full_well_e, which maps to the top code; read noise comes after the well.
    assert (expose(np.full((8, 8), 2.0), full_well_e=1000, read_noise_e=0.0, rng=rng) == 4095).all()
    noisy = expose(np.full((64, 64), 2.0), full_well_e=1000, read_noise_e=2.0, rng=rng)
    assert noisy.max() == 4095 and noisy.mean() == pytest.approx(4095 - 2.0 * 4.095 * 0.4, abs=1.5)


def test_expose_quantisation_ranges_and_colour():
    ramp = np.linspace(-0.2, 1.2, 141).reshape(1, -1)
    q12 = expose(ramp, bit_depth=12, shot_noise=False, read_noise_e=0.0)
    q8 = expose(ramp, bit_depth=8, shot_noise=False, read_noise_e=0.0)
    assert q12.dtype == np.uint16 and q8.dtype == np.uint8
    assert np.abs(q12 - np.clip(ramp * 4095, 0, 4095)).max() <= 0.5 + 1e-9  # rounded to the nearest code
    assert np.abs(q8 - np.clip(ramp * 255, 0, 255)).max() <= 0.5 + 1e-9
    assert q12.min() == 0 and q12.max() == 4095 and q8.max() == 255
    rgb = np.random.default_rng(2).uniform(0, 1, (4, 5, 3))
    mono = to_mono(rgb)
    assert mono.shape == (4, 5) and mono[0, 0] == pytest.approx(rgb[0, 0] @ [0.2126, 0.7152, 0.0722], rel=1e-6)
    np.testing.assert_array_equal(expose(rgb, shot_noise=False, read_noise_e=0),
                                  expose(mono, shot_noise=False, read_noise_e=0))
    assert expose(rgb, rgb=True, shot_noise=False, read_noise_e=0).shape == (4, 5, 3)
    with pytest.raises(InputError):
        expose(mono, rgb=True)


def test_bad_inputs_name_the_field():
    with pytest.raises(InputError, match="PinholeCamera.K"):
        PinholeCamera(np.eye(2), np.eye(3), np.zeros(3), 8, 8)
    with pytest.raises(InputError, match="PinholeCamera.R"):
        PinholeCamera(np.eye(3), 2 * np.eye(3), np.zeros(3), 8, 8)
    with pytest.raises(InputError, match="TexturedMesh.faces"):
        TexturedMesh(np.zeros((3, 3)), [[0, 1, 3]], np.zeros((3, 2)), [1])
    with pytest.raises(InputError, match="TexturedMesh.object_id"):
        TexturedMesh(np.zeros((3, 3)), [[0, 1, 2]], np.zeros((3, 2)), [0])
    mesh = TexturedMesh(np.eye(3), [[0, 1, 2]], np.zeros((3, 2)), [1])
    with pytest.raises(InputError, match="render.atlas"):
        render(mesh, _frontal(8, 8, 10.0), np.ones((4, 4, 2), np.float32))


def test_bench_prints_one_json_line():
    out = subprocess.run([sys.executable, str(REPO / "bench" / "render.py"), "--sizes", "64", "--triangles", "2000",
                          "--no-reference", "--no-cold-compile"], capture_output=True, text=True, timeout=120, cwd=REPO)
    assert out.returncode == 0, out.stderr
    lines = out.stdout.strip().splitlines()
    assert len(lines) == 1, out.stdout
    result = json.loads(lines[0])
    assert result["bench"] == "render" and result["sizes"] == [64] and 1500 < result["triangles"] < 2500
    assert result["64"]["fps"] > 0 and result["64"]["fps_1thread"] > 0 and 0.2 < result["64"]["coverage"] < 0.8


def test_bench_renders_the_rig_scene():
    out = subprocess.run([sys.executable, str(REPO / "bench" / "render.py"), "--scene", "rig", "--sizes", "64",
                          "--no-reference", "--no-cold-compile"], capture_output=True, text=True, timeout=120, cwd=REPO)
    assert out.returncode == 0, out.stderr
    result = json.loads(out.stdout.strip().splitlines()[-1])
    assert result["scene"] == "rig" and result["triangles"] > 5000
    assert result["64"]["fps"] > 0 and result["64"]["structure_coverage"] > 0.03
