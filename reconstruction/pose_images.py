"""The images the poses come from (one frame of each take and the static photos, written as COLMAP reads them,
with their masks) and the intrinsics of their cameras."""
from __future__ import annotations

import logging
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from odsplat.spine.errors import InputError, OdsplatError
from odsplat.spine.store import Capture

from .pose_result import PoseSettings

log = logging.getLogger(__name__)

_STATIC_VIEW = re.compile(r"view_(\d+)$")


@dataclass
class PoseImage:
    name: str            # the pose name: take name or "static/<stem>"
    kind: str            # "take" | "static"
    view: int
    colmap_name: str     # path under the work images folder: takes/NAME.png, static/STEM.png
    image: np.ndarray    # uint8, gray (H, W) or BGR (H, W, 3), as written for COLMAP
    group: tuple[int, int]  # (width, height): images of one size share one camera

    @property
    def gray(self) -> np.ndarray:
        return self.image if self.image.ndim == 2 else cv2.cvtColor(self.image, cv2.COLOR_BGR2GRAY)


def _to_u8(frame: np.ndarray, bit_depth: int) -> np.ndarray:
    """A take frame as 8 bits by its recorded bit depth (12-bit data in uint16 is not scaled by 16 bits)."""
    if frame.dtype == np.uint8:
        return frame
    scale = 255.0 / (2 ** int(bit_depth) - 1)
    return np.clip(np.round(frame.astype(np.float32) * scale), 0, 255).astype(np.uint8)


def collect_images(capture: Capture, settings: PoseSettings) -> tuple[list[PoseImage], list[str]]:
    images, notes = [], []
    for name in (t.name for t in capture.select_takes(settings.takes)):
        with capture.open_take(name) as reader:
            if not reader.has_frames or reader.n_frames == 0:
                notes.append(f"take {name} holds no frames; left out")
                continue
            if settings.frame >= reader.n_frames:
                raise InputError(reader.path, f"frame {settings.frame} asked for; the take has {reader.n_frames}")
            frame = reader.read_frames(settings.frame, settings.frame + 1)[0]
            u8 = _to_u8(frame, reader.bit_depth)
            view = reader.view
        if u8.ndim == 3:
            u8 = cv2.cvtColor(u8, cv2.COLOR_RGB2BGR)  # takes hold RGB, OpenCV writes BGR
        images.append(PoseImage(name, "take", -1 if view is None else view, f"takes/{name}.png", u8,
                                (u8.shape[1], u8.shape[0])))
    if settings.use_static and capture.static_dir.is_dir():
        for path in sorted(capture.static_dir.glob("*.png")):
            img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            if img is None:
                raise InputError(path, "not a readable PNG image")
            if img.dtype == np.uint16:
                img = np.round(img / 257.0).astype(np.uint8)  # static photos are stored at 16-bit full scale
            if img.ndim == 3 and img.shape[2] == 4:
                img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
            match = _STATIC_VIEW.search(path.stem)
            images.append(PoseImage(f"static/{path.stem}", "static", int(match.group(1)) if match else -1,
                                    f"static/{path.name}", img, (img.shape[1], img.shape[0])))
    return images, notes


def write_images(images: Sequence[PoseImage], work: Path, masks_dir: Path | None) -> Path | None:
    for im in tqdm(images, desc="poses: images", unit="image", disable=None, leave=False):
        path = work / "images" / im.colmap_name
        path.parent.mkdir(parents=True, exist_ok=True)
        if not cv2.imwrite(str(path), im.image):
            raise OdsplatError(f"{path}: could not be written")
    if masks_dir is None:
        return None
    if not masks_dir.is_dir():
        raise InputError(masks_dir, "no such masks directory")
    found = 0
    for im in images:
        src = masks_dir / f"{im.name}.png"
        h, w = im.image.shape[:2]
        if src.exists():
            mask = cv2.imread(str(src), cv2.IMREAD_GRAYSCALE)
            if mask is None:
                raise InputError(src, "not a readable mask image")
            if mask.shape != (h, w):
                raise InputError(src, f"mask is {mask.shape[1]}x{mask.shape[0]} px; its image is {w}x{h}")
            found += 1
        else:
            mask = np.full((h, w), 255, np.uint8)  # no mask: features everywhere
        # COLMAP looks for MASKS/<image path>.png
        dst = work / "masks" / f"{im.colmap_name}.png"
        dst.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(dst), mask)
    if not found:
        raise InputError(masks_dir, f"no mask matches an image; expected e.g. {images[0].name}.png"
                         if images else "no images to mask")
    log.info("poses: %d of %d images masked", found, len(images))
    return work / "masks"


@dataclass
class Intrinsics:
    K: np.ndarray                 # OpenCV convention: pixel (0, 0) centred at (0, 0)
    dist: tuple[float, ...] = ()  # OpenCV order

    def colmap(self, *, refined: bool = False) -> tuple[str, list[float]]:
        """COLMAP model name and parameters; COLMAP puts pixel (0, 0)'s centre at (0.5, 0.5). A square-pixel camera
        without distortion that SfM will refine becomes SIMPLE_RADIAL: one focal length and k1, as when estimated."""
        K, d = self.K, list(self.dist)
        base = [K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5]
        if refined and not any(d) and abs(K[0, 0] - K[1, 1]) <= 1e-6 * K[0, 0]:
            return "SIMPLE_RADIAL", [K[0, 0], base[2], base[3], 0.0]
        if not any(d):
            return "PINHOLE", base
        if len(d) == 4 or (len(d) == 5 and d[4] == 0):
            return "OPENCV", base + d[:4]
        if len(d) in (5, 8):
            return "FULL_OPENCV", base + (d + [0.0] * 3)[:8]
        raise InputError("capture.json: camera.intrinsics.dist",
                         f"COLMAP takes 4, 5 or 8 OpenCV distortion coefficients; got {len(d)}")

    @classmethod
    def from_colmap(cls, camera) -> Intrinsics:
        p = [float(v) for v in camera.params]
        model = camera.model_name
        if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
            f, cx, cy, extra = p[0], p[1], p[2], p[3:]
            K = np.array([[f, 0, cx - 0.5], [0, f, cy - 0.5], [0, 0, 1.0]])
            dist = () if model == "SIMPLE_PINHOLE" else tuple((extra + [0.0])[:2]) + (0.0, 0.0)
        elif model in ("PINHOLE", "OPENCV", "FULL_OPENCV"):
            K = np.array([[p[0], 0, p[2] - 0.5], [0, p[1], p[3] - 0.5], [0, 0, 1.0]])
            dist = tuple(p[4:])
        else:
            raise OdsplatError(f"COLMAP camera model {model} is not converted to OpenCV here")
        return cls(K, dist)

    @property
    def cv_dist(self) -> np.ndarray | None:
        return np.asarray(self.dist, np.float64) if any(self.dist) else None


def known_intrinsics(capture: Capture, images: Sequence[PoseImage]) -> dict[tuple[int, int], Intrinsics]:
    """The manifest's intrinsics, for the image size the manifest's camera has (the takes' size if unstated)."""
    cam = capture.manifest.camera
    if cam.intrinsics is None:
        return {}
    if cam.width_px and cam.height_px:
        size = (int(cam.width_px), int(cam.height_px))
    else:
        sizes = {im.group for im in images if im.kind == "take"}
        if len(sizes) != 1:
            return {}
        (size,) = sizes
    k = cam.intrinsics
    return {size: Intrinsics(k.matrix(), tuple(float(d) for d in k.dist))}
