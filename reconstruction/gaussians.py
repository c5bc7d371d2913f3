"""A set of 3D Gaussians as trainable tensors, its initialisation from points, and the INRIA `.ply` layout.

Parameters are stored unconstrained (log scales, opacity and colour logits, unnormalised quaternions) and
exposed through the activations the rasterizer takes. Colour is view-independent (degree-0 only): the
structures we film are matte, and the cameras look at them from a hemisphere with one exposure.
"""
from __future__ import annotations

import hashlib
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from plyfile import PlyData, PlyElement, PlyParseError
from scipy.spatial import cKDTree

from odsplat.spine.atomic import atomic_path
from odsplat.spine.contract import CAPTURE_KEY, check_capture
from odsplat.spine.errors import InputError, SchemaError

SH_C0 = 0.28209479177387814  # the degree-0 spherical-harmonic constant: colour = 0.5 + SH_C0 * f_dc
_FIELDS = ("means", "quats", "log_scales", "opacity_logits", "color_logits")


def _logit(p: np.ndarray, eps: float = 1e-4) -> np.ndarray:
    p = np.clip(p, eps, 1 - eps)
    return np.log(p / (1 - p))


@dataclass
class Gaussians:
    """N Gaussians: means (N,3), quats (N,4) w-x-y-z, log_scales (N,3), opacity_logits (N,), color_logits (N,C)."""

    means: torch.Tensor
    quats: torch.Tensor
    log_scales: torch.Tensor
    opacity_logits: torch.Tensor
    color_logits: torch.Tensor

    def __post_init__(self) -> None:
        n = self.means.shape[0]
        shapes = {"means": (n, 3), "quats": (n, 4), "log_scales": (n, 3), "opacity_logits": (n,)}
        for name, shape in shapes.items():
            if tuple(getattr(self, name).shape) != shape:
                raise InputError(f"Gaussians.{name}", f"expected shape {shape}, got {tuple(getattr(self, name).shape)}")
        if self.color_logits.ndim != 2 or self.color_logits.shape[0] != n:
            raise InputError("Gaussians.color_logits", f"expected shape ({n}, C), got {tuple(self.color_logits.shape)}")

    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def n_colors(self) -> int:
        return int(self.color_logits.shape[1])

    # The activations the rasterizer takes.
    @property
    def scales(self) -> torch.Tensor:
        return torch.exp(self.log_scales)

    @property
    def opacities(self) -> torch.Tensor:
        return torch.sigmoid(self.opacity_logits)

    @property
    def colors(self) -> torch.Tensor:
        return torch.sigmoid(self.color_logits)

    @property
    def unit_quats(self) -> torch.Tensor:
        return self.quats / self.quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)

    def tensors(self) -> dict[str, torch.Tensor]:
        return {name: getattr(self, name) for name in _FIELDS}

    def detached(self) -> Gaussians:
        return Gaussians(**{k: v.detach().clone() for k, v in self.tensors().items()})

    @classmethod
    def from_points(cls, points: np.ndarray, colors: np.ndarray, *, opacity: float = 0.1,
                    min_scale: float = 1e-4, dtype: torch.dtype = torch.float32) -> Gaussians:
        """Isotropic Gaussians at `points`, each as wide as the mean distance to its three nearest neighbours."""
        points = np.asarray(points, float)
        colors = np.asarray(colors, float)
        if points.ndim != 2 or points.shape[1] != 3 or len(points) < 4:
            raise InputError("points", f"expected at least 4 points of shape (P, 3), got {points.shape}")
        if colors.ndim != 2 or len(colors) != len(points):
            raise InputError("colors", f"expected ({len(points)}, C) colours in [0, 1], got {colors.shape}")
        dist, _ = cKDTree(points).query(points, k=4)
        scale = np.maximum(dist[:, 1:].mean(axis=1), min_scale)
        n = len(points)
        t = lambda a: torch.as_tensor(np.asarray(a), dtype=dtype)  # noqa: E731
        return cls(means=t(points), quats=t(np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))),
                   log_scales=t(np.log(np.repeat(scale[:, None], 3, axis=1))),
                   opacity_logits=t(np.full(n, _logit(np.array(opacity)))),
                   color_logits=t(_logit(np.clip(colors, 0.0, 1.0))))

    def transformed(self, scale: float, offset: np.ndarray | torch.Tensor) -> Gaussians:
        """The same Gaussians in coordinates x' = scale * x + offset (scene normalisation and back)."""
        offset = torch.as_tensor(np.asarray(offset), dtype=self.means.dtype)
        return Gaussians(means=self.means * scale + offset, quats=self.quats,
                         log_scales=self.log_scales + np.log(scale), opacity_logits=self.opacity_logits,
                         color_logits=self.color_logits)


# ---------------------------------------------------------------------------------------------------- INRIA .ply
def _ply_names(n_colors_rest: int) -> list[str]:
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    names += [f"f_rest_{i}" for i in range(n_colors_rest)]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    return names


_CAPTURE_COMMENT = f"odsplat {CAPTURE_KEY} "   # the header comment that records the capture a .ply belongs to
_DIGEST_COMMENT = "odsplat sha256 "              # ... and the one that records its vertex data's SHA-256
# What plyfile raises on a file that is not a whole PLY: a bad header (PlyParseError), data cut short (EOFError,
# ValueError), a garbled count or type (MemoryError, OverflowError, KeyError, IndexError), bytes that are not text.
_PLY_ERRORS = (PlyParseError, ValueError, EOFError, OSError, MemoryError, OverflowError, KeyError, IndexError,
               TypeError, struct.error)


def save_ply(g: Gaussians, path: str | Path, *, capture_id: str | None = None) -> Path:
    """Write the INRIA 3DGS layout (binary little-endian float32, through plyfile) that standard splat viewers open.
    A capture's file (`capture_id` given) records in header comments, which viewers ignore, the capture's id and
    its vertex data's SHA-256, which `load_ply` checks: a PLY has no checksum of its own.

    Mono colour goes to all three f_dc channels. Higher SH bands (f_rest_*, 45 of them for degree 3) are written
    as zeros: viewers expect them, and our colour has none.
    """
    path = Path(path)
    with torch.no_grad():
        rgb = g.colors.double().cpu().numpy()
        if rgb.shape[1] == 1:
            rgb = np.repeat(rgb, 3, axis=1)
        elif rgb.shape[1] != 3:
            raise InputError(str(path), f"a .ply holds 1 or 3 colour channels, the Gaussians have {rgb.shape[1]}")
        columns = {
            **dict(zip("xyz", g.means.double().cpu().numpy().T)),
            **{f"f_dc_{i}": c for i, c in enumerate(((rgb - 0.5) / SH_C0).T)},
            "opacity": g.opacity_logits.double().cpu().numpy(),
            **{f"scale_{i}": c for i, c in enumerate(g.log_scales.double().cpu().numpy().T)},
            **{f"rot_{i}": c for i, c in enumerate(g.unit_quats.double().cpu().numpy().T)},
        }
    vertex = np.zeros(len(g), dtype=[(name, "<f4") for name in _ply_names(45)])  # normals and f_rest stay 0
    for name, values in columns.items():
        vertex[name] = values
    comments = [] if capture_id is None else [_CAPTURE_COMMENT + capture_id,
                                              _DIGEST_COMMENT + hashlib.sha256(vertex.tobytes()).hexdigest()]
    ply = PlyData([PlyElement.describe(vertex, "vertex")], text=False, byte_order="<", comments=comments)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            ply.write(fh)
    return path


def load_ply(path: str | Path, *, n_colors: int = 3, dtype: torch.dtype = torch.float32,
             capture_id: str | None = None) -> Gaussians:
    """Read an INRIA-layout `.ply` (ours or another tool's, any PLY encoding plyfile reads); mono when n_colors is 1
    (the mean of f_dc). Given `capture_id`, a file whose header records another capture's is refused; a file whose
    vertex data does not match the SHA-256 its header records is refused as damaged."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "no such .ply file")
    if path.stat().st_size == 0:
        raise SchemaError(path, "empty file (0 bytes), not a PLY file")
    try:
        ply = PlyData.read(str(path), mmap=False)
    except _PLY_ERRORS as exc:
        text = " ".join(str(exc).split())[:200]
        raise SchemaError(path, f"not a readable PLY file, cut short or damaged ({type(exc).__name__}: {text})") \
            from None
    recorded = {}
    for comment in ply.comments:
        for key in (_CAPTURE_COMMENT, _DIGEST_COMMENT):
            if comment.startswith(key):
                recorded[key] = comment[len(key):].strip()
    check_capture(recorded.get(_CAPTURE_COMMENT), path, capture_id)
    if "vertex" not in ply:
        raise SchemaError(path, "not a Gaussian splat .ply (missing element vertex)")
    vertex = ply["vertex"].data
    if _DIGEST_COMMENT in recorded:
        little = vertex.astype(vertex.dtype.newbyteorder("<"))
        if hashlib.sha256(little.tobytes()).hexdigest() != recorded[_DIGEST_COMMENT]:
            raise SchemaError(path, "its vertex data does not match the SHA-256 its header records (damaged or "
                                    "edited); run its stage again")
    props = vertex.dtype.names or ()
    missing = [p for p in _ply_names(0) if p not in props and p not in ("nx", "ny", "nz")]
    if missing:
        raise SchemaError(path, f"not a Gaussian splat .ply (missing {missing})")
    not_float = [p for p in _ply_names(0) if p in props and vertex.dtype[p].kind != "f"]
    if not_float:
        raise SchemaError(path, f"property {not_float[0]}: expected float, got {vertex.dtype[not_float[0]]}")

    def col(name: str) -> np.ndarray:
        return vertex[name].astype(np.float64)

    def stack(*names: str) -> torch.Tensor:
        return torch.as_tensor(np.stack([col(n) for n in names], axis=1), dtype=dtype)

    rgb = 0.5 + SH_C0 * np.stack([col("f_dc_0"), col("f_dc_1"), col("f_dc_2")], axis=1)
    colors = rgb.mean(axis=1, keepdims=True) if n_colors == 1 else rgb
    return Gaussians(means=stack("x", "y", "z"), quats=stack(*(f"rot_{i}" for i in range(4))),
                     log_scales=stack(*(f"scale_{i}" for i in range(3))),
                     opacity_logits=torch.as_tensor(col("opacity"), dtype=dtype),
                     color_logits=torch.as_tensor(_logit(np.clip(colors, 0.0, 1.0)), dtype=dtype))


__all__ = ["Gaussians", "SH_C0", "load_ply", "save_ply"]
