"""Tests of reconstruction.raster: the torch tile path and the numba path against the brute-force reference,
gradients, geometry against OpenCV, the compositing rules by hand, culling, background and argument checks."""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch

from odsplat.reconstruction.raster import RasterOutput, rasterize, rasterize_image, rasterize_reference
from odsplat.spine.errors import InputError

OUTPUTS = ("image", "alpha", "depth", "extras")
TILED = ("torch", "numba")  # the back ends that bin into tiles; "reference" is what they are checked against


def _rot_y(angle: float, dtype) -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]], dtype=dtype)


def random_scene(n: int, width: int, height: int, dtype=torch.float64, seed: int = 0, dense: bool = False):
    """Gaussians 1-5 units in front of a turned, shifted camera with an off-centre principal point: 5 % behind it,
    5 % inside the near plane, centres spread over 1.5x the view (partly off-screen), the last 5 % large, a few
    with opacity above the 0.99 clamp. `dense` raises opacities so that many pixels reach early termination."""
    g = torch.Generator().manual_seed(seed)
    f = 0.9 * width
    K = torch.tensor([[f, 0, (width - 1) / 2 + 1.3], [0, 1.05 * f, (height - 1) / 2 - 0.7], [0, 0, 1]], dtype=dtype)
    z = 1.0 + 4.0 * torch.rand(n, generator=g, dtype=dtype)
    half = torch.tensor([width / f, height / (1.05 * f)], dtype=dtype)
    xy = (torch.rand(n, 2, generator=g, dtype=dtype) - 0.5) * 1.5 * half * z[:, None]
    cam = torch.cat([xy, z[:, None]], 1)
    cam[: n // 20, 2] *= -1
    cam[n // 20: n // 10, 2] = 0.005
    view = torch.eye(4, dtype=dtype)
    view[:3, :3], view[:3, 3] = _rot_y(0.1, dtype), torch.tensor([0.1, -0.2, 0.3], dtype=dtype)
    scales = torch.exp(0.5 * torch.randn(n, 3, generator=g, dtype=dtype)) * 0.02 * z[:, None] * (2.0 if dense else 1.0)
    scales[-(n // 20):] *= 8
    opac = (0.6 if dense else 0.05) + (0.39 if dense else 0.9) * torch.rand(n, generator=g, dtype=dtype)
    opac[n // 10: n // 10 + 5] = 0.995
    params = {"means": (cam - view[:3, 3]) @ view[:3, :3], "quats": torch.randn(n, 4, generator=g, dtype=dtype),
              "scales": scales, "opacities": opac, "colors": torch.rand(n, 3, generator=g, dtype=dtype),
              "viewmat": view, "K": K}
    return params, torch.rand(3, generator=g, dtype=dtype), torch.rand(n, 2, generator=g, dtype=dtype)


def _max_diff(a: RasterOutput, b: RasterOutput) -> dict[str, float]:
    return {k: float((getattr(a, k) - getattr(b, k)).detach().abs().max()) for k in OUTPUTS}


@pytest.mark.parametrize("backend", TILED)
@pytest.mark.parametrize("dtype,tol", [(torch.float32, 1e-6), (torch.float64, 1e-12)])
@pytest.mark.parametrize("size", [(37, 23), (64, 48)])
@pytest.mark.parametrize("tile_px", [16, 8])
def test_tiles_match_reference(dtype, tol, size, tile_px, backend, monkeypatch):
    """In float32 the numba path (which projects in float64) is held to the float64 reference of the same inputs,
    the torch path (which projects like the reference) to the float32 reference."""
    from odsplat.reconstruction import raster

    w, h = size
    for dense in (False, True):
        params, bg, extras = random_scene(300, w, h, dtype, seed=w + tile_px, dense=dense)
        as_ref = (lambda t: t.double()) if backend == "numba" else (lambda t: t)  # noqa: E731
        ref = rasterize_reference(**{k: as_ref(v) for k, v in params.items()}, width_px=w, height_px=h,
                                  background=as_ref(bg), extras=as_ref(extras))
        out = rasterize(**params, width_px=w, height_px=h, background=bg, extras=extras, tile_px=tile_px,
                        backend=backend)
        u, v = out.means2d.unbind(-1)
        partly_off = (out.radii_px > 0) & ((u < 0) | (u > w - 1) | (v < 0) | (v > h - 1))
        assert int(partly_off.sum()) >= 3 and int((out.radii_px == 0).sum()) >= 30  # the scene is what it claims
        diff = _max_diff(out, ref)
        scale = max(1.0, float(ref.depth.abs().max()))
        assert max(diff.values()) <= tol * scale, diff
        assert torch.equal(out.radii_px, ref.radii_px) and out.radii_px.dtype == torch.int32
        if dense:  # early termination did act: without it the image changes
            with monkeypatch.context() as m:
                m.setattr(raster, "T_MIN", 0.0)
                unstopped = rasterize(**params, width_px=w, height_px=h, background=bg, extras=extras, tile_px=tile_px,
                                      backend=backend)
            assert float((unstopped.image - out.image).abs().max()) > 1e-5


def _grads(backend: str, params, bg, extras, weights):
    leaves = {k: v.clone().requires_grad_(k != "K") for k, v in params.items()}
    bg, extras = bg.clone().requires_grad_(True), extras.clone().requires_grad_(True)
    w, h = weights.shape[1], weights.shape[0]
    out = rasterize(**leaves, width_px=w, height_px=h, background=bg, extras=extras, tile_px=8, backend=backend)
    out.means2d.retain_grad()
    loss = ((out.image * weights).sum() + 0.1 * (out.depth * weights[..., 0]).sum()
            + (out.extras ** 2).sum() + (out.alpha * weights[..., 1]).sum())
    loss.backward()
    grads = {k: v.grad for k, v in leaves.items() if k != "K"}
    return {**grads, "background": bg.grad, "extras": extras.grad, "means2d": out.means2d.grad}


@pytest.mark.parametrize("backend,tol", [("torch", 1e-10), ("numba", 1e-12)])
@pytest.mark.parametrize("dense", [False, True])
def test_tile_gradients_match_reference(dense, backend, tol):
    params, bg, extras = random_scene(300, 37, 23, torch.float64, seed=5, dense=dense)
    weights = torch.rand(23, 37, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    ours, ref = _grads(backend, params, bg, extras, weights), _grads("reference", params, bg, extras, weights)
    for k, g in ref.items():
        assert torch.isfinite(ours[k]).all(), k
        scale = float(g.abs().max())
        assert scale > 0, k
        assert float((ours[k] - g).abs().max()) <= tol * scale, k


def test_numba_float32_agrees_with_torch():
    """Training runs in float32: the numba path (float64 projection and sums) and the torch path (float32 throughout)
    agree to float32 rounding in the images and in every gradient, early termination included."""
    params, bg, extras = random_scene(400, 48, 40, torch.float32, seed=9, dense=True)
    weights = torch.rand(40, 48, 3, generator=torch.Generator().manual_seed(3))
    outs = {b: rasterize(**params, width_px=48, height_px=40, background=bg, extras=extras, backend=b)
            for b in TILED}
    for k in OUTPUTS:
        a, b = getattr(outs["numba"], k), getattr(outs["torch"], k)
        assert a.dtype == torch.float32 and float((a - b).abs().max()) <= 1e-5 * max(1.0, float(b.abs().max())), k
    assert float(outs["torch"].alpha.max()) > 1 - 1e-3  # pixels that stop early
    ours, theirs = _grads("numba", params, bg, extras, weights), _grads("torch", params, bg, extras, weights)
    for k, g in theirs.items():
        assert ours[k].dtype == torch.float32, k
        assert float((ours[k] - g).abs().max()) <= 1e-5 * float(g.abs().max()), k


def test_numba_gradients_do_not_depend_on_the_thread_count():
    """Each (Gaussian, tile) pair has its own gradient row and the rows are added in a fixed order."""
    params, bg, extras = random_scene(300, 64, 48, torch.float32, seed=8, dense=True)
    weights = torch.rand(48, 64, 3, generator=torch.Generator().manual_seed(4))
    threads = torch.get_num_threads()
    runs = []
    for n in (1, 2):
        torch.set_num_threads(n)
        try:
            runs.append(_grads("numba", params, bg, extras, weights))
            assert torch.get_num_threads() == n  # starting numba's threads leaves torch's count alone
        finally:
            torch.set_num_threads(threads)
    for k, g in runs[0].items():
        assert torch.equal(g, runs[1][k]), k


def test_auto_on_cpu_is_numba_for_float32_and_float64():
    for dtype in (torch.float32, torch.float64):
        params, bg, extras = random_scene(100, 24, 16, dtype, seed=10)
        auto = rasterize(**params, width_px=24, height_px=16, background=bg, extras=extras)
        numba = rasterize(**params, width_px=24, height_px=16, background=bg, extras=extras, backend="numba")
        assert all(torch.equal(getattr(auto, k), getattr(numba, k)) for k in OUTPUTS)
    params, _, _ = random_scene(10, 16, 12, torch.float16, seed=1)
    with pytest.raises(InputError) as err:
        rasterize(**params, width_px=16, height_px=12, backend="numba")
    assert err.value.source == "means" and "float32 or float64" in err.value.problem


def test_small_chunks_and_recomputation_change_nothing(monkeypatch):
    """Chunks of a few tiles, or of part of a row in the reference, recomputed in backward (checkpointing),
    give the same images and gradients as the default single chunk kept in memory."""
    from odsplat.reconstruction import raster

    params, bg, extras = random_scene(300, 37, 23, torch.float64, seed=6, dense=True)
    weights = torch.rand(23, 37, 3, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    default = {b: _grads(b, params, bg, extras, weights) for b in ("torch", "reference")}
    monkeypatch.setattr(raster, "_CHUNK_PAIRS", 2000)
    monkeypatch.setattr(raster, "_SAVED_BUDGET_BYTES", 0)
    calls = []

    def counted(*args, **kwargs):
        calls.append(1)
        return torch.utils.checkpoint.checkpoint(*args, **kwargs)

    monkeypatch.setattr(raster, "checkpoint", counted)
    for backend, grads in default.items():
        n_calls = len(calls)
        small = _grads(backend, params, bg, extras, weights)
        assert len(calls) - n_calls >= 15, backend  # one tile, or a part of a row, per recomputed chunk
        for k, g in grads.items():
            assert float((small[k] - g).abs().max()) <= 1e-12 * float(g.abs().max()), (backend, k)


def _tiny_scene():
    """4 Gaussians on 10 x 8 px, chosen so that no (pixel, Gaussian) pair sits within a finite-difference step of
    a cutoff (q = 9, alpha = 1/255, the 0.99 clamp) and T stays far above 1e-4 (asserted in the test)."""
    dt = torch.float64
    K = torch.tensor([[9.0, 0, 4.6], [0, 9.5, 3.4], [0, 0, 1]], dtype=dt)
    view = torch.eye(4, dtype=dt)
    view[:3, :3], view[:3, 3] = _rot_y(0.05, dt), torch.tensor([0.02, -0.03, 0.1], dtype=dt)
    means = torch.tensor([[0.1, 0.05, 1.6], [-0.15, 0.1, 2.0], [0.2, -0.12, 2.4], [0.0, 0.0, 3.0]], dtype=dt)
    quats = torch.tensor([[0.9, 0.1, -0.2, 0.3], [0.7, 0.3, 0.2, -0.1], [0.5, -0.5, 0.4, 0.2], [1.0, 0.2, 0.1, 0.0]],
                         dtype=dt)
    scales = 3 * torch.tensor([[0.2, 0.12, 0.15], [0.16, 0.25, 0.1], [0.3, 0.2, 0.25], [0.22, 0.3, 0.18]], dtype=dt)
    opac = torch.tensor([0.6, 0.45, 0.7, 0.55], dtype=dt)
    colors = torch.tensor([[0.9, 0.1], [0.2, 0.8], [0.5, 0.5], [0.3, 0.6]], dtype=dt)
    extras = torch.tensor([[1.0], [0.0], [0.5], [0.25]], dtype=dt)
    return means, quats, scales, opac, colors, view, K, torch.tensor([0.2, 0.4], dtype=dt), extras


@pytest.mark.parametrize("backend", TILED)
def test_gradcheck_tiles(backend):
    means, quats, scales, opac, colors, view, K, bg, extras = _tiny_scene()
    w, h = 10, 8
    out = rasterize_reference(means, quats, scales, opac, colors, view, K, w, h)
    # margins of every pair from the cutoffs, with the same projection
    from odsplat.reconstruction.raster import _project
    p = _project(means, quats, scales, view, K, w, h, 0.01)
    ys, xs = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    dx, dy = xs[..., None] - p.means2d[:, 0], ys[..., None] - p.means2d[:, 1]
    q = -2 * (p.conics[:, 0] * dx * dx + p.conics[:, 1] * dx * dy + p.conics[:, 2] * dy * dy)
    a = opac * torch.exp(-q / 2)
    assert float((q - 9).abs().min()) > 0.1 and float((a * 255 - 1).abs().min()) > 0.05 and float(a.max()) < 0.9
    assert float(out.alpha.max()) < 0.99 and float((out.alpha > 0.05).double().mean()) > 0.9  # nearly all pixels

    def render(means, quats, scales, opac, colors, bg, extras):
        o = rasterize(means, quats, scales, opac, colors, view, K, w, h, background=bg, extras=extras, tile_px=4,
                      backend=backend)
        return o.image, o.alpha, o.depth, o.extras

    inputs = tuple(t.clone().requires_grad_(True) for t in (means, quats, scales, opac, colors, bg, extras))
    assert torch.autograd.gradcheck(render, inputs, eps=1e-6, atol=1e-7, rtol=1e-5)


@pytest.mark.parametrize("backend", ["torch", "numba", "reference"])
def test_compositing_rules_by_hand(backend):
    """Five Gaussians on one line of sight through pixel (3, 2), given out of depth order: the second in depth
    clamps at 0.99, the fourth would take T below 1e-4, so it and the fifth are dropped."""
    dt = torch.float64
    K = torch.tensor([[10.0, 0, 3.0], [0, 10.0, 2.0], [0, 0, 1]], dtype=dt)
    z = torch.tensor([3.0, 1.0, 5.0, 2.0, 4.0], dtype=dt)
    opac = torch.tensor([0.7, 0.5, 0.1, 0.995, 0.97], dtype=dt)
    colors = torch.tensor([[3.0], [1.0], [5.0], [2.0], [4.0]], dtype=dt)
    means = torch.stack([torch.zeros_like(z), torch.zeros_like(z), z], -1)
    out = rasterize(means, torch.tensor([[1.0, 0, 0, 0]] * 5, dtype=dt), 0.05 * z[:, None].expand(5, 3).clone(),
                    opac, colors, torch.eye(4, dtype=dt), K, 7, 5, background=torch.tensor([10.0], dtype=dt),
                    extras=torch.arange(5, dtype=dt)[:, None], backend=backend, tile_px=4)
    a = [0.5, 0.99, 0.7]  # depth order 1, 2, 3 (colors 1, 2, 3); 4 (T after 1.5e-3 * 0.03 < 1e-4) and 5 dropped
    t = [1.0, 0.5, 0.005]
    w = [a[i] * t[i] for i in range(3)]
    t_final = 0.005 * 0.3
    assert float(out.image[2, 3, 0]) == pytest.approx(w[0] * 1 + w[1] * 2 + w[2] * 3 + 10 * t_final, abs=1e-12)
    assert float(out.depth[2, 3]) == pytest.approx(w[0] * 1 + w[1] * 2 + w[2] * 3, abs=1e-12)
    assert float(out.alpha[2, 3]) == pytest.approx(1 - t_final, abs=1e-12)
    assert float(out.extras[2, 3, 0]) == pytest.approx(w[0] * 1 + w[1] * 3 + w[2] * 0, abs=1e-12)


def _camera():
    K = np.array([[55.0, 0, 22.3], [0, 57.0, 18.9], [0, 0, 1]])
    rvec, tvec = np.array([0.1, -0.2, 0.05]), np.array([0.2, -0.1, 1.0])
    view = np.eye(4)
    view[:3, :3], view[:3, 3] = cv2.Rodrigues(rvec)[0], tvec
    return K, rvec, tvec, view


def _one(point_w, sigma, opacity, K, view, w, h, dtype=torch.float64, backend="auto") -> RasterOutput:
    t = lambda x: torch.tensor(np.asarray(x), dtype=dtype)  # noqa: E731
    return rasterize(t([point_w]), t([[1.0, 0, 0, 0]]), t([[sigma] * 3]), t([opacity]), t([[1.0]]), t(view), t(K), w, h,
                     backend=backend)


@pytest.mark.parametrize("backend", TILED)
def test_centroid_at_opencv_projection(backend):
    K, rvec, tvec, view = _camera()
    w, h = 48, 40
    rng = np.random.default_rng(3)
    errs = []
    for _ in range(8):
        pc = np.array([rng.uniform(-0.25, 0.25), rng.uniform(-0.2, 0.2), rng.uniform(1.5, 2.5)])
        pw = view[:3, :3].T @ (pc - tvec)
        uv = cv2.projectPoints(pw[None], rvec, tvec, K, None)[0].reshape(2)
        img = _one(pw, 2.0 * pc[2] / K[0, 0], 0.5, K, view, w, h, backend=backend).image[..., 0].numpy()  # ~2 px
        ys, xs = np.mgrid[:h, :w]
        errs.append(np.abs(np.array([(img * xs).sum(), (img * ys).sum()]) / img.sum() - uv).max())
    assert max(errs) < 0.02, errs


@pytest.mark.parametrize("backend", TILED)
def test_depth_and_alpha_at_centre_pixel(backend):
    K, _, tvec, view = _camera()
    z = 2.3
    pc = np.array([(17 - K[0, 2]) * z / K[0, 0], (21 - K[1, 2]) * z / K[1, 1], z])  # onto pixel (17, 21)
    out = _one(view[:3, :3].T @ (pc - tvec), 0.02, 0.99, K, view, 48, 40, torch.float32, backend)
    assert float(out.alpha[21, 17]) == pytest.approx(0.99, abs=1e-6)
    assert float(out.depth[21, 17] / out.alpha[21, 17]) == pytest.approx(z, rel=1e-4)
    assert float(out.depths[0]) == pytest.approx(z, rel=1e-6)
    assert float(out.alpha[21, 19]) < 0.9  # and it is a small Gaussian, not a flat field


@pytest.mark.parametrize("backend", TILED)
def test_projected_covariance_by_hand(backend):
    """Sigma2 on the optical axis (J = diag(f/z) there): the 0.3 px^2 dilation, the scales' axes and the
    (w, x, y, z) quaternion; off to the sides: J's x/z clamped to [-(cx + 0.5)/fx, (W - 0.5 - cx)/fx] widened by
    0.3 W/(2 fx) on each side."""
    dt = torch.float64
    w, h, f, z, o = 40, 30, 20.0, 2.0, 0.8
    K = torch.tensor([[f, 0, 19.0], [0, f, 14.0], [0, 0, 1]], dtype=dt)

    def alpha(mean, quat, scale):
        t = lambda x: torch.tensor([x], dtype=dt)  # noqa: E731
        return rasterize(t(mean), t(quat), t(scale), t(o)[0:1], torch.ones(1, 1, dtype=dt), torch.eye(4, dtype=dt),
                         K, w, h, backend=backend)

    sx, sy = (f * 0.05 / z) ** 2 + 0.3, (f * 0.1 / z) ** 2 + 0.3  # px^2 along x and y
    on_axis = alpha([0.0, 0.0, z], [1.0, 0.0, 0.0, 0.0], [0.05, 0.1, 0.3])
    assert float(on_axis.alpha[14, 20]) == pytest.approx(o * math.exp(-0.5 / sx), abs=1e-12)
    assert float(on_axis.alpha[16, 19]) == pytest.approx(o * math.exp(-2.0 / sy), abs=1e-12)
    assert float(on_axis.alpha[15, 20]) == pytest.approx(o * math.exp(-0.5 / sx - 0.5 / sy), abs=1e-12)
    assert int(on_axis.radii_px[0]) == math.ceil(3 * math.sqrt(sy))
    # a quarter turn about the camera's z axis, quaternion (cos 45, 0, 0, sin 45): the scales swap axes
    turned = alpha([0.0, 0.0, z], [math.sqrt(0.5), 0.0, 0.0, math.sqrt(0.5)], [0.05, 0.1, 0.3])
    assert float(turned.alpha[14, 21]) == pytest.approx(o * math.exp(-2.0 / sy), abs=1e-12)
    assert float(turned.alpha[16, 19]) == pytest.approx(o * math.exp(-2.0 / sx), abs=1e-12)
    # centre at x/z = 2, beyond the right edge; J sees x/z = (40 - 0.5 - 19)/20 + 0.3 * 1 = 1.325
    side = alpha([2.0 * z, 0.0, z], [1.0, 0.0, 0.0, 0.0], [1.0, 1.0, 1.0])
    var_x, var_y = (f / z) ** 2 * (1 + 1.325 ** 2) + 0.3, (f / z) ** 2 + 0.3
    u = 2.0 * f + 19.0
    assert float(side.alpha[15, 35]) == pytest.approx(o * math.exp(-0.5 * ((35 - u) ** 2 / var_x + 1 / var_y)),
                                                      abs=1e-12)
    assert float(side.alpha[15, 35]) > 0.05
    # and beyond the left edge: x/z = -(19 + 0.5)/20 - 0.3 = -1.275
    side = alpha([-2.0 * z, 0.0, z], [1.0, 0.0, 0.0, 0.0], [1.0, 1.0, 1.0])
    var_x, u = (f / z) ** 2 * (1 + 1.275 ** 2) + 0.3, -2.0 * f + 19.0
    assert float(side.alpha[15, 3]) == pytest.approx(o * math.exp(-0.5 * ((3 - u) ** 2 / var_x + 1 / var_y)),
                                                     abs=1e-12)


@pytest.mark.parametrize("backend", ["torch", "numba", "reference"])
@pytest.mark.parametrize("opacity", [0.1, 0.8])
def test_cutoffs_by_hand(opacity, backend):
    """One isotropic Gaussian on the optical axis (Sigma2 = (s^2 + 0.3) I exactly): alpha is o exp(-q/2) where
    q <= 9 and that is >= 1/255, else 0. At o = 0.1 the 1/255 cutoff binds (at q = 6.5), at o = 0.8 the q = 9 one.
    Two more left of the image: radius 0 when the box ends half a pixel short of column 0, not when it reaches
    half a pixel past it (though q > 9 there: it adds nothing)."""
    dt = torch.float64
    w, h, f, z, sigma = 40, 30, 20.0, 2.0, 0.35
    K = torch.tensor([[f, 0, 19.3], [0, f, 14.6], [0, 0, 1]], dtype=dt)
    var = (f * sigma / z) ** 2 + 0.3
    r = math.ceil(3 * math.sqrt(var))
    var_side = (f * sigma / z) ** 2 * (1 + (19.8 / f + 0.3) ** 2) + 0.3  # J's x/z clamped at -(19.3 + 0.5)/20 - 0.3
    r_side = math.ceil(3 * math.sqrt(var_side))
    us = [19.3, -r_side - 0.5, -r_side + 0.5]
    means = torch.tensor([[(u - 19.3) * z / f, 0.0, z] for u in us], dtype=dt)
    out = rasterize(means, torch.tensor([[1.0, 0, 0, 0]] * 3, dtype=dt), torch.full((3, 3), sigma, dtype=dt),
                    torch.full((3,), opacity, dtype=dt), torch.ones(3, 1, dtype=dt), torch.eye(4, dtype=dt), K, w, h,
                    backend=backend)
    ys, xs = torch.meshgrid(torch.arange(h, dtype=dt), torch.arange(w, dtype=dt), indexing="ij")
    q = ((xs - 19.3) ** 2 + (ys - 14.6) ** 2) / var
    a = opacity * torch.exp(-q / 2)
    assert float((q - 9).abs().min()) > 1e-3 and float((a * 255 - 1).abs().min()) > 1e-3  # no pixel on an edge
    inside = (q <= 9) & (a >= 1 / 255)
    assert float((out.alpha - torch.where(inside, a, torch.zeros_like(a))).abs().max()) < 1e-12
    assert (int(inside.sum()) < int((q <= 9).sum())) == (opacity < 0.2)
    assert out.radii_px.tolist() == [r, 0, r_side]


@pytest.mark.parametrize("backend", TILED)
@pytest.mark.parametrize("front", [0, 1])
def test_extras_as_segmentation(front, backend):
    """A wide Gaussian (id 0) and a narrow one (id 1) whose centre lies inside the wide one's core; one-hot
    extras. The front one must win wherever its own alpha exceeds 1/2 (then a_f > (1 - a_f) a_b for any
    a_b <= 0.99), the narrow one's centre included; far left only the wide one reaches."""
    dt = torch.float64
    z = torch.tensor([2.0, 3.0] if front == 0 else [3.0, 2.0], dtype=dt)
    K = torch.tensor([[30.0, 0, 19.5], [0, 30.0, 12.0], [0, 0, 1]], dtype=dt)
    means = torch.stack([(torch.tensor([17.0, 20.0], dtype=dt) - 19.5) * z / 30, torch.zeros(2, dtype=dt), z], -1)
    scales = (torch.tensor([4.0, 2.5], dtype=dt) * z / 30)[:, None].expand(2, 3).clone()
    args = (torch.tensor([[1.0, 0, 0, 0]] * 2, dtype=dt), scales, torch.tensor([0.99, 0.99], dtype=dt),
            torch.ones(2, 1, dtype=dt), torch.eye(4, dtype=dt), K, 40, 24)
    out = rasterize(means, *args, extras=torch.eye(2, dtype=dt), backend=backend)
    label = out.extras.argmax(-1)
    sel = torch.arange(2) == front
    alone = rasterize(means[sel], *(a[sel] if i < 4 else a for i, a in enumerate(args)), backend=backend).alpha
    core = alone > 0.5
    assert int(core.sum()) > 20 and bool((label[core] == front).all())
    assert int(label[12, 20]) == front and int(label[12, 11]) == 0 and float(out.extras[12, 11, 1]) == 0.0
    assert int((label == 1 - front)[out.alpha > 0.5].sum()) > 0  # the one behind still shows somewhere


def test_culled_gaussians_contribute_nothing_and_get_zero_gradients():
    params, bg, extras = random_scene(60, 32, 24, torch.float64, seed=2)
    near = 0.01
    view = params["viewmat"]
    cam_z = torch.tensor([near, near / 2, 0.0, -1.0], dtype=torch.float64)  # z = near is culled too
    cam = torch.stack([torch.full_like(cam_z, 0.01), torch.full_like(cam_z, -0.02), cam_z], -1)
    culled = (cam - view[:3, 3]) @ view[:3, :3]
    keep = {k: v.clone() for k, v in params.items()}
    both = dict(params)
    dt = torch.float64
    for k, extra in (("means", culled), ("quats", torch.randn(4, 4, dtype=dt)),
                     ("scales", torch.full((4, 3), 0.05, dtype=dt)), ("opacities", torch.full((4,), 0.9, dtype=dt)),
                     ("colors", torch.ones(4, 3, dtype=dt))):
        both[k] = torch.cat([params[k], extra]).requires_grad_(True)
    ex_all = torch.cat([extras, torch.ones(4, 2, dtype=torch.float64)]).requires_grad_(True)
    for backend in ("torch", "numba", "reference"):
        out = rasterize(**both, width_px=32, height_px=24, background=bg, extras=ex_all, near=near, backend=backend)
        ref = rasterize(**keep, width_px=32, height_px=24, background=bg, extras=extras, near=near, backend=backend)
        assert max(_max_diff(out, ref).values()) <= 1e-12
        assert out.radii_px[-4:].tolist() == [0, 0, 0, 0]
        (out.image.sum() + out.depth.sum() + out.extras.sum()).backward()
        for k in ("means", "quats", "scales", "opacities", "colors"):
            g = both[k].grad
            assert torch.isfinite(g).all() and float(g[-4:].abs().max()) == 0.0, k
            assert float(g[:-4].abs().max()) > 0, k
            both[k].grad = None
        assert float(ex_all.grad[-4:].abs().max()) == 0.0
        ex_all.grad = None


@pytest.mark.parametrize("backend", ["torch", "numba", "reference"])
def test_empty_scene_and_background(backend):
    dt = torch.float64
    bg = torch.tensor([0.2, 0.5, 0.9], dtype=dt, requires_grad=True)
    empty = [torch.zeros(0, k, dtype=dt) for k in (3, 4, 3)] + [torch.zeros(0, dtype=dt), torch.zeros(0, 3, dtype=dt)]
    out = rasterize(*empty, torch.eye(4, dtype=dt), torch.eye(3, dtype=dt) * 10, 9, 7, background=bg,
                    extras=torch.zeros(0, 2, dtype=dt), backend=backend)
    assert out.image.shape == (7, 9, 3) and torch.equal(out.image, bg.detach().expand(7, 9, 3))
    assert float(out.alpha.abs().max()) == 0 and float(out.depth.abs().max()) == 0 and out.extras.shape == (7, 9, 2)
    out.image.sum().backward()
    assert bg.grad.tolist() == [63.0, 63.0, 63.0]
    # with Gaussians, the background enters as (1 - alpha) * background
    params, bg2, _ = random_scene(80, 24, 16, dt, seed=4)
    with_bg = rasterize(**params, width_px=24, height_px=16, background=bg2, backend=backend)
    without = rasterize(**params, width_px=24, height_px=16, backend=backend)
    assert torch.allclose(with_bg.image, without.image + (1 - without.alpha)[..., None] * bg2, atol=1e-13)
    assert float(without.alpha.max()) > 0.5 and without.extras is None


def _bad(**change):
    params, bg, extras = random_scene(10, 16, 12, torch.float32, seed=1)
    args = {**params, "width_px": 16, "height_px": 12, "background": bg, "extras": extras}
    args.update(change)
    return args


@pytest.mark.parametrize("change,source", [
    ({"backend": "cuda"}, "backend"),
    ({"means": torch.zeros(10, 2)}, "means"),
    ({"quats": torch.zeros(10, 3)}, "quats"),
    ({"scales": torch.zeros(9, 3)}, "scales"),
    ({"opacities": torch.zeros(10, 1)}, "opacities"),
    ({"opacities": torch.zeros(10, dtype=torch.float64)}, "opacities"),
    ({"colors": torch.zeros(11, 3)}, "colors"),
    ({"viewmat": torch.eye(3)}, "viewmat"),
    ({"K": torch.eye(4)}, "K"),
    ({"background": torch.zeros(4)}, "background"),
    ({"extras": torch.zeros(10)}, "extras"),
    ({"width_px": 0}, "width_px"),
    ({"tile_px": 2.5}, "tile_px"),
    ({"near": -0.1}, "near"),
])
def test_bad_arguments_name_the_argument(change, source):
    with pytest.raises(InputError) as err:
        rasterize(**_bad(**change))
    assert err.value.source == source
    assert "expected" in err.value.problem
    if source == "backend":
        assert all(b in err.value.problem for b in ("auto", "numba", "torch", "reference", "gsplat", "'cuda'"))


@pytest.mark.parametrize("dense", [False, True])
@pytest.mark.parametrize("dtype,tol", [(torch.float32, 1e-6), (torch.float64, 1e-12)])
def test_the_forward_only_image_is_the_numba_paths(dtype, tol, dense):
    """rasterize_image (numpy in and out, nothing kept for backward; the viewer's) gives rasterize's image and
    alpha on the numba path."""
    params, bg, _ = random_scene(300, 64, 48, dtype=dtype, dense=dense)
    with torch.no_grad():
        want = rasterize(**params, width_px=64, height_px=48, background=bg, backend="numba")
    image, alpha = rasterize_image(*(params[k].numpy() for k in ("means", "quats", "scales", "opacities", "colors",
                                                                 "viewmat", "K")), 64, 48, background=bg.numpy(),
                                   backend="numba")
    assert image.dtype == want.image.numpy().dtype
    assert np.abs(image - want.image.numpy()).max() <= tol
    assert np.abs(alpha - want.alpha.numpy()).max() <= tol
    assert (alpha > 0.5).mean() > (0.3 if dense else 0.02)
