"""Aligned takes, `derived/sync/NAME.h5`: a take's frames on the capture's common impact-locked time grid, computed
from the raw take as they are read. The file holds how to compute them, not the frames (a seed-size capture's
aligned frames would be as large as its raw takes: noise does not compress).

Layout (HDF5): attributes `kind` (`KIND`), `schema_version` (`SCHEMA`), `capture_id`, `generation` (sync's run, as
sync.json records it), `take`, `view`, `offset_s`, `method`, `impulse_scale`, `grid_shift_frames` (where grid frame 0
falls among the take's frames, dropped frames counted), `bit_depth`, `n_frames`, `half_taps` and `kaiser_beta` (the
filter); datasets, each Fletcher-32 checked: `times_s` (n,), each grid frame's mid-exposure time after the impact
onset; `source_frame`, the take's frames with the dropped ones put back in counter order: the raw frame index of
each, -1 where dropped; `rest_dn`, the mean rest frame, where the motion is scaled to the capture's impulse
(`impulse_scale` not 1).

Reading a grid frame g: the frames around g + grid_shift_frames (a dropped one filled linearly from its neighbours
in time, the ends mirrored), through a 2 x `HALF_TAPS` tap Kaiser-windowed sinc (band-limited fractional delay: a
sinusoid up to 0.42 of the frame rate keeps its amplitude within 2e-4, `tests/sync/test_aligned.py`); then the
motion scaled about the rest frame. Memory: the frames asked for plus the filter's reach (31 frames), whatever the
take's length; a reader going forward decodes each raw frame once.
"""
from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from odsplat.spine.contract import CAPTURE_KEY
from odsplat.spine.errors import InputError, SchemaError
from odsplat.spine.framefile import ALIGNED_KIND, H5_ERRORS, atomic_h5, check_header
from odsplat.spine.store import Capture

KIND = ALIGNED_KIND
SCHEMA = 4          # 4: the frames computed from the raw take on reading (3 stored them)
HALF_TAPS = 16      # the filter's taps each side of the sample: 32 in all
KAISER_BETA = 8.0
READ_FRAMES = 64    # the longest run of grid frames computed at once

Spatial = Callable[[np.ndarray], np.ndarray]


def delay_taps(frac: float, half: int = HALF_TAPS, beta: float = KAISER_BETA) -> tuple[np.ndarray, np.ndarray]:
    """(offsets k, weights h) with sum_k h[k] x[n + k] = x(n + frac) for a band-limited x; the weights sum to 1, and
    frac 0 gives the identity."""
    if frac == 0.0:
        return np.zeros(1, int), np.ones(1)
    k = np.arange(-half + 1, half + 1)
    x = k - frac
    window = np.i0(beta * np.sqrt(np.clip(1.0 - (x / (half + 0.5)) ** 2, 0.0, 1.0))) / np.i0(beta)
    h = np.sinc(x) * window
    return k, h / h.sum()


def mirror(index: np.ndarray, n: int) -> np.ndarray:
    """Indices outside 0..n-1 reflected about the ends, the end sample repeated (x[-1] = x[0], x[n] = x[n-1])."""
    period = 2 * n
    i = np.mod(index, period)
    return np.where(i < n, i, period - 1 - i)


def write_aligned(path: Path, *, take: str, times_s: np.ndarray, source_frame: np.ndarray, grid_shift_frames: float,
                  bit_depth: int, rest_dn: np.ndarray | None, attrs: dict[str, Any], capture_id: str) -> None:
    """The take's alignment, written whole or not at all (temporary file, fsync, rename)."""
    with atomic_h5(path) as f:
        f.attrs.update(kind=KIND, schema_version=SCHEMA, take=take, bit_depth=int(bit_depth),
                       grid_shift_frames=float(grid_shift_frames), half_taps=HALF_TAPS, kaiser_beta=KAISER_BETA,
                       **{k: v for k, v in attrs.items() if v is not None})
        f.attrs[CAPTURE_KEY] = capture_id
        f.attrs["n_frames"] = len(times_s)
        f.create_dataset("times_s", data=np.asarray(times_s, float), chunks=True, fletcher32=True)
        f.create_dataset("source_frame", data=np.asarray(source_frame, np.int64), chunks=True, fletcher32=True)
        if rest_dn is not None:
            f.create_dataset("rest_dn", data=np.asarray(rest_dn, np.float32), chunks=True, fletcher32=True)


def _filter(x: np.ndarray, weights: np.ndarray, n: int, block: int = 16) -> np.ndarray:
    """y[i] = sum_j weights[j] x[i + j] for i < n, as a banded matrix product per `block` output frames (a BLAS
    product: 3-4 ms per 1024^2 frame on this machine against 35 ms for one pass per tap)."""
    taps = len(weights)
    flat = x.reshape(len(x), -1)
    y = np.empty((n, flat.shape[1]), np.float32)
    band = np.zeros((block, block + taps - 1), np.float32)
    for i in range(block):
        band[i, i:i + taps] = weights
    for a in range(0, n, block):
        b = min(a + block, n)
        y[a:b] = band[:b - a, :b - a + taps - 1] @ flat[a:b + taps - 1]
    return y.reshape(n, *x.shape[1:])


class AlignedTake:
    """Reads an aligned take: frames as float32 in the raw take's DN, on the common grid, computed from the raw take.

    `generation`: sync.json's; a file of another run is refused. Whatever is wrong with the file or its raw take is
    one line naming it."""

    WHAT = "aligned take file"

    def __init__(self, capture: Capture, path: str | Path, generation: str | None = None):
        self.path = Path(path)
        try:
            with h5py.File(self.path, "r") as f:
                self._read_recipe(f, generation, capture.id)
        except FileNotFoundError:
            raise InputError(self.path, "no such aligned take (run `odsplat sync` first)") from None
        except (InputError, SchemaError):
            raise
        except H5_ERRORS as exc:
            raise InputError(self.path, f"not a readable {self.WHAT}, cut short or damaged ({type(exc).__name__}: "
                                        f"{' '.join(str(exc).split())[:200]}); run `odsplat sync` again") from None
        self._raw = capture.open_take(self._attrs["take"])
        problem = None
        if self._source.max(initial=-1) >= self._raw.n_frames:
            problem = (f"lists raw frames up to {self._source.max()}, but take {self._attrs['take']!r} has "
                       f"{self._raw.n_frames}")
        elif self._rest is not None and self._rest.shape != tuple(self._raw.frame_shape):
            problem = f"rest_dn is {self._rest.shape}, the take's frames {tuple(self._raw.frame_shape)}"
        if problem:
            self._raw.close()
            raise InputError(self.path, f"{problem}: run `odsplat sync` again")
        self._memo: tuple[int, np.ndarray] = (0, np.zeros((0, *self.frame_shape), np.float32))

    def _read_recipe(self, f: h5py.File, generation: str | None, capture_id: str) -> None:
        attrs = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f.attrs.items()}
        check_header(attrs, self.path, kinds=(KIND,), schema=SCHEMA, what=self.WHAT, generation=generation,
                     capture_id=capture_id, again="run `odsplat sync` again")
        for key in ("times_s", "source_frame"):
            if not isinstance(f.get(key), h5py.Dataset) or f[key].ndim != 1:
                raise InputError(self.path, f"no {key} (one value per frame); run `odsplat sync` again")
        self._times = f["times_s"][()].astype(float)
        if len(self._times) != attrs.get("n_frames"):
            raise InputError(f"{self.path}: times_s", f"expected {attrs.get('n_frames')} times, one per frame, got "
                                                      f"{len(self._times)}; run `odsplat sync` again")
        self._source = f["source_frame"][()].astype(np.int64)
        present = np.flatnonzero(self._source >= 0)
        if not len(present) or not len(self._times):
            raise InputError(self.path, "no frames to align; run `odsplat sync` again")
        self._rest = f["rest_dn"][()].astype(np.float32) if "rest_dn" in f else None
        self._attrs = attrs
        shift = float(attrs["grid_shift_frames"])
        self._whole = int(np.floor(shift))
        self._offsets, self._weights = delay_taps(shift - self._whole, int(attrs["half_taps"]),
                                                  float(attrs["kaiser_beta"]))
        self._weights = self._weights.astype(np.float32)
        # each filled frame: the two raw frames it is made of and the second's weight (a dropped frame's neighbours
        # in time; one stored frame is itself)
        j = np.arange(len(self._source))
        r = np.searchsorted(present, j)
        lo, hi = present[np.clip(r - 1, 0, len(present) - 1)], present[np.clip(r, 0, len(present) - 1)]
        kept = self._source >= 0
        w = np.where(hi > lo, (j - lo) / np.maximum(hi - lo, 1), 0.0)
        self._w_hi = np.where(kept, 0.0, w).astype(np.float32)
        self._lo, self._hi = self._source[np.where(kept, j, lo)], self._source[np.where(kept, j, hi)]

    @property
    def attrs(self) -> dict[str, Any]:
        return dict(self._attrs)

    @property
    def n_frames(self) -> int:
        return len(self._times)

    @property
    def frame_shape(self) -> tuple[int, ...]:
        return tuple(self._raw.frame_shape)

    @property
    def times_s(self) -> np.ndarray:
        return self._times.copy()

    def _raw_range(self, a: int, b: int) -> np.ndarray:
        """Raw frames a..b-1 as float32; what the previous read decoded is reused (a reader going forward reads
        each raw frame once, whatever the filter's overlap)."""
        have_a, have = self._memo
        parts = []
        if have_a <= a < have_a + len(have):
            parts.append(have[a - have_a:b - have_a])
        start = a + (len(parts[0]) if parts else 0)
        if start < b:
            try:
                parts.append(np.asarray(self._raw.read_frames(start, b), np.float32))
            except H5_ERRORS as exc:
                raise InputError(self._raw.path, f"frames {start}-{b - 1}: unreadable "
                                                 f"({' '.join(str(exc).split())[:200]})") from None
        out = parts[0] if len(parts) == 1 else np.concatenate(parts)
        self._memo = (a, out)
        return out

    def read_frames(self, start: int = 0, stop: int | None = None, spatial: Spatial | None = None) -> np.ndarray:
        """Grid frames start..stop-1, (n, H, W[, C]) float32 DN. `spatial`: a linear map of one frame (a resize, a
        choice of pixels), applied before the time filter: the same result for less work on fewer pixels. A long
        range goes READ_FRAMES at a time: the raw frames in memory are those of one chunk, whatever is asked for
        (a seed-size take read whole through a crop held 10 GB)."""
        stop = self.n_frames if stop is None else min(stop, self.n_frames)
        if not 0 <= start <= stop:
            raise InputError(self.path, f"frame range {start}:{stop} outside 0:{self.n_frames}")
        if start == stop:
            return np.zeros((0, *self.frame_shape), np.float32)
        if stop - start > READ_FRAMES:
            return np.concatenate([self._read(a, min(a + READ_FRAMES, stop), spatial)
                                   for a in range(start, stop, READ_FRAMES)])
        return self._read(start, stop, spatial)

    def _read(self, start: int, stop: int, spatial: Spatial | None) -> np.ndarray:
        filled = mirror(np.arange(start + self._whole + self._offsets[0], stop + self._whole + self._offsets[-1]),
                        len(self._source))
        lo, hi, w = self._lo[filled], self._hi[filled], self._w_hi[filled]
        a, b = int(min(lo.min(), hi.min())), int(max(lo.max(), hi.max())) + 1
        raw = self._raw_range(a, b)
        if lo[0] + len(lo) == b and np.all(np.diff(lo) == 1) and not w.any():
            x = raw[lo[0] - a:]                        # the common case: a run of stored frames, no copy
        else:                                          # the ends (mirrored) or dropped frames (filled)
            x = raw[lo - a]
            for i in np.flatnonzero(w):
                x[i] = (1 - w[i]) * x[i] + w[i] * raw[hi[i] - a]
        if spatial is not None:
            x = np.stack([spatial(frame) for frame in x])
        y = x[:stop - start].copy() if len(self._weights) == 1 else _filter(x, self._weights, stop - start)
        scale = float(self._attrs.get("impulse_scale") or 1.0)
        if scale != 1.0 and self._rest is not None:
            rest = self._rest if spatial is None else spatial(self._rest)
            y = rest + (y - rest) * scale
        return y

    def iter_frames(self, chunk_frames: int = 16, spatial: Spatial | None = None) -> Iterator[np.ndarray]:
        for k in range(0, self.n_frames, chunk_frames):
            yield self.read_frames(k, k + chunk_frames, spatial)

    def close(self) -> None:
        self._memo = (0, self._memo[1][:0])
        self._raw.close()

    def __enter__(self) -> AlignedTake:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


__all__ = ["AlignedTake", "delay_taps", "mirror", "write_aligned"]
