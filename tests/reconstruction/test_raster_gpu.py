"""The gsplat back end against the reference (CUDA only), and how the back end is chosen where gsplat cannot run."""
from __future__ import annotations

import importlib.abc
import sys

import pytest
import torch

from odsplat.reconstruction import raster
from odsplat.reconstruction.raster import gsplat_available, rasterize
from odsplat.spine.errors import InputError

from .test_raster import random_scene

needs_gsplat = pytest.mark.skipif(not (torch.cuda.is_available() and gsplat_available()),
                                  reason="needs CUDA and gsplat")


class _Import(importlib.abc.MetaPathFinder):
    """Records imports of gsplat and optionally fails them the way a broken build would."""

    def __init__(self, error: Exception | None):
        self.error, self.attempts = error, 0

    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] != "gsplat":
            return None
        self.attempts += 1
        if self.error is not None:
            raise self.error
        return None


@pytest.fixture
def gsplat_import(monkeypatch):
    """A fresh gsplat_available() whose imports of gsplat go through an _Import hook."""
    hooks = []

    def install(error: Exception | None) -> _Import:
        hook = _Import(error)
        monkeypatch.setattr(sys, "meta_path", [hook, *sys.meta_path])
        monkeypatch.delitem(sys.modules, "gsplat", raising=False)
        hooks.append(hook)
        return hook

    gsplat_available.cache_clear()
    yield install
    gsplat_available.cache_clear()


def test_gsplat_unavailable_without_cuda_never_imports_it(gsplat_import, monkeypatch):
    hook = gsplat_import(RuntimeError("nvcc: compiling the CUDA extension failed"))
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert gsplat_available() is False
    assert hook.attempts == 0


@pytest.mark.parametrize("error", [ImportError("No module named 'gsplat'"), RuntimeError("a failed build")])
def test_gsplat_unavailable_when_its_import_fails(gsplat_import, monkeypatch, error):
    hook = gsplat_import(error)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert gsplat_available() is False
    assert hook.attempts == 1


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks a machine without CUDA")
def test_gsplat_unavailable_here():
    gsplat_available.cache_clear()
    assert gsplat_available() is False
    with pytest.raises(InputError) as err:
        params, _, _ = random_scene(10, 16, 12, torch.float32)
        rasterize(**params, width_px=16, height_px=12, backend="gsplat")
    assert err.value.source == "backend"


def test_auto_on_cpu_tensors_takes_the_numba_path(monkeypatch):
    def refuse(*args, **kwargs):
        raise AssertionError("the gsplat path was taken for CPU tensors")

    # even with gsplat reported available, CPU tensors must not go to it
    monkeypatch.setattr(raster, "gsplat_available", lambda: True)
    monkeypatch.setattr(raster, "_rasterize_gsplat", refuse)
    params, bg, extras = random_scene(200, 37, 23, torch.float32, seed=3)
    auto = rasterize(**params, width_px=37, height_px=23, background=bg, extras=extras)
    tiles = rasterize(**params, width_px=37, height_px=23, background=bg, extras=extras, backend="numba")
    for k in ("image", "alpha", "depth", "extras"):
        assert torch.equal(getattr(auto, k), getattr(tiles, k)), k
    assert float(auto.alpha.max()) > 0.5


def _gsplat_scene():
    """Opacities below 0.35 so that a >= 1/255 implies q < 9 (gsplat has no q cutoff) and a stays under both
    clamps (ours 0.99, gsplat's 0.999); few enough layers that T never nears 1e-4; centres inside the view so
    that J's clamp, whose limits differ between gsplat versions, never acts."""
    params, bg, extras = random_scene(300, 64, 48, torch.float64, seed=7)
    keep = params["opacities"] < 2  # every one; then drop those behind, inside near, or off-centre
    view, K = params["viewmat"], params["K"]
    cam = params["means"] @ view[:3, :3].T + view[:3, 3]
    uv = cam[:, :2] / cam[:, 2:] * torch.stack([K[0, 0], K[1, 1]]) + torch.stack([K[0, 2], K[1, 2]])
    keep &= (cam[:, 2] > 0.5) & (uv[:, 0] > 2) & (uv[:, 0] < 61) & (uv[:, 1] > 2) & (uv[:, 1] < 45)
    params = {k: (v[keep] if v.shape[0] == len(keep) and k not in ("viewmat", "K") else v) for k, v in params.items()}
    params["opacities"] = 0.05 + 0.29 * torch.rand(int(keep.sum()), generator=torch.Generator().manual_seed(2),
                                                   dtype=torch.float64)
    return params, bg, extras[keep]


def _render_with_grads(backend, params, bg, extras, weights, dtype):
    dev = torch.device("cuda")
    leaf = lambda t: t.detach().to(dev, dtype).clone()  # noqa: E731
    leaves = {k: leaf(v).requires_grad_(k not in ("viewmat", "K")) for k, v in params.items()}
    bg, extras = leaf(bg).requires_grad_(True), leaf(extras).requires_grad_(True)
    out = rasterize(**leaves, width_px=64, height_px=48, background=bg, extras=extras, backend=backend)
    out.means2d.retain_grad()
    w = weights.to(dev, dtype)
    ((out.image * w).sum() + 0.1 * (out.depth * w[..., 0]).sum() + (out.extras * w[..., 1:]).sum()
     + (out.alpha * w[..., 2]).sum()).backward()
    grads = {k: v.grad.double() for k, v in leaves.items() if k not in ("viewmat", "K")}
    grads.update(background=bg.grad.double(), extras=extras.grad.double(), means2d=out.means2d.grad.double())
    return out, grads


@pytest.mark.gpu
@needs_gsplat
def test_gsplat_matches_reference():
    params, bg, extras = _gsplat_scene()
    weights = torch.rand(48, 64, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    ref, ref_grads = _render_with_grads("reference", params, bg, extras, weights, torch.float64)
    ours, our_grads = _render_with_grads("gsplat", params, bg, extras, weights, torch.float32)
    assert float((1 - ref.alpha).min()) > 1e-3 and float(ref.alpha.max()) > 0.5  # no early termination; not empty
    for k in ("image", "alpha", "depth", "extras"):
        a, b = getattr(ours, k).double(), getattr(ref, k)
        assert float((a - b).abs().max()) <= 2e-4 * max(1.0, float(b.abs().max())), k
    assert float((ours.means2d.double() - ref.means2d).abs().max()) < 1e-3
    visible = ref.radii_px > 0
    # gsplat may trim a faint Gaussian's radius by its opacity, never widen it
    assert bool((ours.radii_px[visible] > 0).all()) and bool((ours.radii_px <= ref.radii_px + 1).all())
    for k, g in ref_grads.items():
        scale = float(g.abs().max())
        assert scale > 0, k
        assert float((our_grads[k] - g).abs().max()) <= 2e-3 * scale, k
