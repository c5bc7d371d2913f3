"""The viewpoint plan of a guided capture session: where the camera goes for each take, how far an actual pose is
from its plan, how much of the band the takes so far cover, and what to tell the engineer (docs/capture-plan.md)."""
from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from odsplat.spine.errors import InputError
from odsplat.spine.geometry import (
    camera_center_m,
    look_at,
    rotation_angle_deg,
    spherical_coords,
    spherical_eye,
    viewing_angle_deg,
)
from odsplat.spine.manifest import Viewpoint

GOLDEN_ANGLE_DEG = 180.0 * (3.0 - math.sqrt(5.0))  # 137.507...: successive spiral points never line up
COVERAGE_SAMPLES = 2000  # directions sampling the band in `coverage`
COVERAGE_RADIUS_FACTOR = 0.75  # default coverage radius, as a fraction of the plan's typical neighbour spacing


def _finite(source: str, value) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise InputError(source, f"expected a number, got {value!r}")
    if not math.isfinite(value):
        raise InputError(source, f"expected a finite number, got {value!r}")
    return float(value)


@dataclass(frozen=True)
class PlanSettings:
    """What the plan covers: n_views on a sphere of radius_m around target_m (world, floor z = 0), between the
    elevations elevation_deg = (low, high) above the horizontal through the target; azimuth_offset_deg turns
    the whole plan about the vertical through the target."""

    n_views: int = 27
    radius_m: float = 1.6
    elevation_deg: tuple[float, float] = (15.0, 60.0)
    target_m: tuple[float, float, float] = (0.2, 0.0, 0.3)
    azimuth_offset_deg: float = 0.0

    def __post_init__(self) -> None:
        if isinstance(self.n_views, bool) or not isinstance(self.n_views, (int, np.integer)) or self.n_views < 1:
            raise InputError("PlanSettings.n_views", f"expected an integer >= 1, got {self.n_views!r}")
        radius = _finite("PlanSettings.radius_m", self.radius_m)
        if radius <= 0:
            raise InputError("PlanSettings.radius_m", f"expected a distance > 0, got {self.radius_m!r}")
        try:
            lo, hi = self.elevation_deg
        except (TypeError, ValueError):
            raise InputError("PlanSettings.elevation_deg",
                             f"expected (low, high) in degrees, got {self.elevation_deg!r}") from None
        lo = _finite("PlanSettings.elevation_deg", lo)
        hi = _finite("PlanSettings.elevation_deg", hi)
        if not 0 <= lo < hi < 90:
            raise InputError("PlanSettings.elevation_deg", f"expected 0 <= low < high < 90 degrees, got ({lo}, {hi})")
        try:
            target = tuple(_finite("PlanSettings.target_m", v) for v in self.target_m)
        except TypeError:
            raise InputError("PlanSettings.target_m", f"expected (x, y, z) in metres, got {self.target_m!r}") from None
        if len(target) != 3:
            raise InputError("PlanSettings.target_m", f"expected (x, y, z) in metres, got {self.target_m!r}")
        if target[2] < 0:
            raise InputError("PlanSettings.target_m",
                             f"the target must be at or above the floor (z >= 0), got z = {target[2]}")
        offset = _finite("PlanSettings.azimuth_offset_deg", self.azimuth_offset_deg)
        for name, value in (("n_views", int(self.n_views)), ("radius_m", radius), ("elevation_deg", (lo, hi)),
                            ("target_m", target), ("azimuth_offset_deg", offset)):
            object.__setattr__(self, name, value)


def _band(n: int, lo_deg: float, hi_deg: float, offset_deg: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """(azimuth_deg, elevation_deg) of n golden-angle spiral points over the band, equal-area (uniform in
    sin(elevation), each point in the middle of its slice), lowest first."""
    i = np.arange(n, dtype=np.float64)
    s_lo, s_hi = math.sin(math.radians(lo_deg)), math.sin(math.radians(hi_deg))
    elevation = np.degrees(np.arcsin(s_lo + (i + 0.5) / n * (s_hi - s_lo)))
    azimuth = (offset_deg + i * GOLDEN_ANGLE_DEG) % 360.0
    return azimuth, elevation


def _directions(azimuth_deg, elevation_deg) -> np.ndarray:
    az, el = np.radians(np.asarray(azimuth_deg, float)), np.radians(np.asarray(elevation_deg, float))
    return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=-1).reshape(-1, 3)


def _angles_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Great-circle angles between unit vectors, (len(a), len(b))."""
    return np.degrees(np.arccos(np.clip(a @ b.T, -1.0, 1.0)))


def _walk(dist: np.ndarray) -> list[int]:
    """A short open path through all points starting at point 0: greedy nearest neighbour, then 2-opt."""
    n = len(dist)
    path, left = [0], set(range(1, n))
    while left:
        here = path[-1]
        nxt = min(left, key=lambda k: (dist[here, k], k))
        path.append(nxt)
        left.remove(nxt)
    improved = True
    while improved:
        improved = False
        for i in range(1, n - 1):
            for j in range(i + 1, n):
                # reverse path[i..j]; the edge after j only exists when j is not the last point
                before = dist[path[i - 1], path[i]] + (dist[path[j], path[j + 1]] if j + 1 < n else 0.0)
                after = dist[path[i - 1], path[j]] + (dist[path[i], path[j + 1]] if j + 1 < n else 0.0)
                if after < before - 1e-9:
                    path[i:j + 1] = path[i:j + 1][::-1]
                    improved = True
    return path


def plan_views(settings: PlanSettings = PlanSettings()) -> list[Viewpoint]:
    """The planned viewpoints, indexed 0..n-1 in walking order: starting at the lowest view, each next view is
    close to the previous one (nearest neighbour walk shortened by 2-opt, great-circle distance)."""
    lo, hi = settings.elevation_deg
    azimuth, elevation = _band(settings.n_views, lo, hi, settings.azimuth_offset_deg)
    dirs = _directions(azimuth, elevation)
    order = _walk(_angles_deg(dirs, dirs))
    return [Viewpoint(index=k, azimuth_deg=float(azimuth[i]), elevation_deg=float(elevation[i]),
                      distance_m=settings.radius_m, target_m=list(settings.target_m))
            for k, i in enumerate(order)]


def view_eye_m(viewpoint: Viewpoint) -> np.ndarray:
    """The planned camera centre of a viewpoint, in world metres."""
    return spherical_eye(viewpoint.azimuth_deg, viewpoint.elevation_deg, viewpoint.distance_m, viewpoint.target_m)


def view_pose(viewpoint: Viewpoint) -> tuple[np.ndarray, np.ndarray]:
    """The planned world-to-camera pose (R, t) of a viewpoint: at its eye, aimed at its target, world z up."""
    return look_at(view_eye_m(viewpoint), viewpoint.target_m)


@dataclass(frozen=True)
class PoseCheck:
    """How an actual camera pose compares with its planned viewpoint (degrees and metres)."""

    angular_error_deg: float   # angle at the target between the planned and the actual camera centre
    distance_error_m: float    # actual minus planned distance to the target (> 0: too far)
    azimuth_error_deg: float   # actual minus planned azimuth, wrapped to (-180, 180] (> 0: too far towards +y)
    elevation_error_deg: float  # actual minus planned elevation (> 0: too high)
    azimuth_deg: float         # actual azimuth, [0, 360)
    elevation_deg: float       # actual elevation
    distance_m: float          # actual distance to the target
    aim_error_deg: float       # angle between the optical axis and the ray from the camera to the target
    rotation_error_deg: float  # angle of R_actual R_planned^T (includes roll about the optical axis)


def check_pose(viewpoint: Viewpoint, R_actual, t_actual) -> PoseCheck:
    """Compare an actual world-to-camera pose (e.g. from the AprilTag boards) with its planned viewpoint."""
    target = np.asarray(viewpoint.target_m, dtype=np.float64)
    center = camera_center_m(R_actual, t_actual)
    azimuth, elevation, distance = spherical_coords(center, target)
    d_az = (azimuth - viewpoint.azimuth_deg) % 360.0
    d_az = d_az - 360.0 if d_az > 180.0 else d_az
    R_actual = np.asarray(R_actual, dtype=np.float64)
    to_target = (target - center) / distance
    axis = R_actual[2]  # the optical axis in world coordinates
    aim = math.degrees(math.atan2(float(np.linalg.norm(np.cross(axis, to_target))), float(axis @ to_target)))
    R_planned, _ = view_pose(viewpoint)
    return PoseCheck(
        angular_error_deg=viewing_angle_deg(view_eye_m(viewpoint), center, target),
        distance_error_m=distance - viewpoint.distance_m,
        azimuth_error_deg=d_az,
        elevation_error_deg=elevation - viewpoint.elevation_deg,
        azimuth_deg=azimuth,
        elevation_deg=elevation,
        distance_m=distance,
        aim_error_deg=aim,
        rotation_error_deg=rotation_angle_deg(R_actual, R_planned),
    )


def _az_el(done: Iterable[Viewpoint | Sequence[float]]) -> tuple[np.ndarray, np.ndarray]:
    az, el = [], []
    for k, item in enumerate(done):
        if isinstance(item, Viewpoint):
            az.append(item.azimuth_deg)
            el.append(item.elevation_deg)
        else:
            try:
                a, e = item
            except (TypeError, ValueError):
                raise InputError(f"coverage.done[{k}]",
                                 f"expected a Viewpoint or (azimuth_deg, elevation_deg), got {item!r}") from None
            az.append(_finite(f"coverage.done[{k}]", a))
            el.append(_finite(f"coverage.done[{k}]", e))
    return np.asarray(az, float), np.asarray(el, float)


def neighbour_spacing_deg(views: Sequence[Viewpoint]) -> np.ndarray:
    """Each view's great-circle angle to its nearest other view, in degrees (empty for fewer than two views)."""
    az, el = _az_el(views)
    if len(az) < 2:
        return np.zeros(0)
    dirs = _directions(az, el)
    angles = _angles_deg(dirs, dirs)
    np.fill_diagonal(angles, np.inf)
    return angles.min(axis=1)


def default_coverage_radius_deg(settings: PlanSettings) -> float:
    """COVERAGE_RADIUS_FACTOR times the full plan's median nearest-neighbour spacing (for one view: the spacing
    an equal-area hexagonal layout of the band would have)."""
    spacing = neighbour_spacing_deg(plan_views(settings))
    if len(spacing):
        typical = float(np.median(spacing))
    else:
        lo, hi = (math.radians(e) for e in settings.elevation_deg)
        area_sr = 2 * math.pi * (math.sin(hi) - math.sin(lo)) / settings.n_views
        typical = math.degrees(math.sqrt(2 * area_sr / math.sqrt(3)))
    return COVERAGE_RADIUS_FACTOR * typical


def coverage(done: Sequence[Viewpoint | Sequence[float]], settings: PlanSettings = PlanSettings(), *,
             radius_deg: float | None = None) -> float:
    """Fraction of the planned band (COVERAGE_SAMPLES equal-area directions) within radius_deg of a done view.

    `done` holds Viewpoints or (azimuth_deg, elevation_deg) pairs; distances are ignored. The default radius is
    `default_coverage_radius_deg(settings)`.
    """
    if radius_deg is None:
        radius_deg = default_coverage_radius_deg(settings)
    elif _finite("coverage.radius_deg", radius_deg) <= 0:
        raise InputError("coverage.radius_deg", f"expected an angle > 0, got {radius_deg!r}")
    az, el = _az_el(done)
    if len(az) == 0:
        return 0.0
    lo, hi = settings.elevation_deg
    samples = _directions(*_band(COVERAGE_SAMPLES, lo, hi))
    nearest_cos = (samples @ _directions(az, el).T).max(axis=1)
    return float(np.mean(nearest_cos >= math.cos(math.radians(radius_deg))))


def _index_of(source: str, item: int | Viewpoint, known: set[int]) -> int:
    index = item.index if isinstance(item, Viewpoint) else item
    if isinstance(index, bool) or not isinstance(index, (int, np.integer)) or index not in known:
        raise InputError(source, f"view {index!r} is not among the views drawn (indices {sorted(known)})")
    return int(index)


def top_view_map(views: Sequence[Viewpoint], settings: PlanSettings = PlanSettings(), *,
                 done: Iterable[int | Viewpoint] = (), current: int | Viewpoint | None = None,
                 width: int = 41, height: int = 21) -> str:
    """ASCII map of the views seen from above, centred on the target: x to the right, y up.

    The first `height` lines are the map, `width` characters each: '#' the structure (target), 'o' a planned
    view, '*' a done one, '@' the current one, '.' the circle the lowest views stand on, '-' and '|' the axes
    through the target. Every view gets exactly one mark; a view whose cell is taken goes to the nearest free
    cell. Two legend lines follow.
    """
    if isinstance(width, bool) or not isinstance(width, int) or width < 11:
        raise InputError("top_view_map.width", f"expected an integer >= 11, got {width!r}")
    if isinstance(height, bool) or not isinstance(height, int) or height < 5:
        raise InputError("top_view_map.height", f"expected an integer >= 5, got {height!r}")
    known = {v.index for v in views}
    done_set = {_index_of(f"top_view_map.done[{k}]", d, known) for k, d in enumerate(done)}
    current_index = None if current is None else _index_of("top_view_map.current", current, known)
    if len(views) > width * height - 3:
        raise InputError("top_view_map", f"{len(views)} views do not fit on a {width}x{height} map")

    target = np.asarray(settings.target_m, dtype=np.float64)
    offsets = [view_eye_m(v)[:2] - target[:2] for v in views]
    ring_m = settings.radius_m * math.cos(math.radians(settings.elevation_deg[0]))
    extent_m = max([ring_m] + [float(np.hypot(*o)) for o in offsets])
    cx, cy = width // 2, height // 2
    # the outermost column and row carry the axis arrows; views stay inside them
    sx, sy = (min(cx, width - 1 - cx) - 1) / extent_m, (min(cy, height - 1 - cy) - 1) / extent_m

    grid = [[" "] * width for _ in range(height)]
    for a in np.linspace(0.0, 2 * math.pi, 8 * (width + height), endpoint=False):
        grid[cy - round(ring_m * math.sin(a) * sy)][cx + round(ring_m * math.cos(a) * sx)] = "."
    for col in range(width):
        grid[cy][col] = "-"
    for row in range(height):
        grid[row][cx] = "|"
    grid[cy][cx], grid[cy][width - 1], grid[0][cx] = "#", ">", "^"
    taken = {(cy, cx), (cy, width - 1), (0, cx)}

    cells = [(r, c) for r in range(height) for c in range(width)]
    counts = {"o": 0, "*": 0, "@": 0}
    for view, (dx, dy) in zip(views, offsets):
        want = (cy - round(dy * sy), cx + round(dx * sx))
        if want in taken:  # nearest free cell, with rows counted twice as far as columns (character aspect)
            want = min((cell for cell in cells if cell not in taken),
                       key=lambda cell: (2 * (cell[0] - want[0])) ** 2 + (cell[1] - want[1]) ** 2)
        taken.add(want)
        mark = "@" if view.index == current_index else "*" if view.index in done_set else "o"
        grid[want[0]][want[1]] = mark
        counts[mark] += 1

    now = "" if current_index is None else f", @ current (view {current_index + 1}, index {current_index})"
    lines = ["".join(row) for row in grid]
    lines.append(f"top view: x -> (azimuth 0 deg), y ^ (azimuth 90 deg); # target at x={target[0]:.2f}, "
                 f"y={target[1]:.2f} m; . circle r={ring_m:.2f} m")
    lines.append(f"o planned ({counts['o']}), * done ({counts['*']}){now}")
    return "\n".join(lines)


def describe_view(viewpoint: Viewpoint, n_views: int | None = None) -> str:
    """One line telling the engineer where to put the camera for this view."""
    eye = view_eye_m(viewpoint)
    target = viewpoint.target_m
    horizontal = viewpoint.distance_m * math.cos(math.radians(viewpoint.elevation_deg))
    number = f"view {viewpoint.index + 1}" + ("" if n_views is None else f"/{n_views}") + f" (index {viewpoint.index})"
    return (f"{number}: azimuth {viewpoint.azimuth_deg:.0f} deg (from +x towards +y), elevation "
            f"{viewpoint.elevation_deg:.0f} deg, {viewpoint.distance_m:.2f} m from the target "
            f"(camera at x={eye[0]:.2f}, y={eye[1]:.2f}, z={eye[2]:.2f} m: {horizontal:.2f} m out along the floor, "
            f"{eye[2]:.2f} m above it); aim at the target x={target[0]:.2f}, y={target[1]:.2f}, z={target[2]:.2f} m")
