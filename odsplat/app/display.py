"""The settings of the two commands that show a reconstruction, `odsplat render` and `odsplat view`, checked by
themselves (like the stages' settings), so the flags and any other entry refuse the same values with one line."""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

from odsplat.app.viewer import default_state
from odsplat.app.viewer.model import ALPHA_RANGE, start_time_s, visible_alpha
from odsplat.reconstruction import check_camera_spec
from odsplat.spine.checks import (
    MAX_DURATION_S,
    MAX_MAGNIFICATION,
    PLAYBACK_FPS,
    WIDTH_PX,
    Range,
    check_choice,
    check_fields,
    maybe,
)
from odsplat.spine.errors import InputError

COLOURS = ("image", "displacement")
MAX_EXPORT_FRAMES = 10_000      # the window's frames box goes as far
MAX_VIEW_PX = 8192              # a view's width or height


@dataclass(frozen=True)
class RenderSettings:
    """What `odsplat render` draws: cameras, times, size and magnification."""

    camera: str = "orbit"           # a take name (its estimated pose), orbit[:N[:ELEVATION_DEG[:DISTANCE_M]]], or a
    #                                 JSON camera path
    times: str = "all"              # 'all' (the trained timesteps), 'A:B:N' (N times from A to B s) or 'a,b,c' (s after
    #                                 the impact)
    width_px: int | None = None     # image width in px (None: the camera's)
    alpha: float | None = None      # magnification to show (None: as trained, the frames' own); scales every
    #                                 Gaussian's displacement and rotation from rest: any factor, no retraining
    fps: float = 30.0               # frame rate of the mp4
    mp4: bool = True                # also write render.mp4 beside the PNG frames

    def __post_init__(self) -> None:

        # alpha 0 shows the rest state; above, the 2D magnification's bound (MAGNIFICATION), so one number rules both.
        check_fields(self, {"alpha": maybe(Range(at_least=0, at_most=MAX_MAGNIFICATION)), "width_px": maybe(WIDTH_PX),
                            "fps": PLAYBACK_FPS})
        if not isinstance(self.camera, str) or not isinstance(self.times, str):
            raise InputError("RenderSettings.camera", "expected the camera and the times as text")
        check_camera_spec(self.camera)


@dataclass(frozen=True)
class ViewSettings:
    """What `odsplat view` shows, and how an export is written."""

    n_frames: int = 48                      # frames of the export
    fps: float = 24.0                       # frame rate of the export
    alpha: float | None = None              # magnification in 3D, 1 to 10^5 (displacements and rotations from rest
    #                                         times alpha): the window's slider (viewer.model.ALPHA_RANGE); None: the
    #                                         one that moves the structure 5 % of its size (viewer.visible_alpha)
    mode: int | None = None                 # animate mode K (1-based, the analysis's numbering) at its frequency; the
    #                                         export is one cycle
    ods: int | None = None                  # animate ODS line K (1-based, the analysis's lines) at its frequency, per
    #                                         newton of harmonic force
    motion: bool = False                    # the measured motion over the reconstruction's time (the default)
    time_s: float | None = None             # time in s after the impact (screenshot)
    turntable: bool = False                 # the export's camera turns once around the structure
    camera: int | None = None               # look through capture camera N (from 0)
    structure_only: bool = False            # hide what does not move (the floor, the background)
    surface: bool = False                   # draw the structure as its surface (triangles over the analysis's
    #                                         surface points, as the report's 3D shapes), not as its Gaussians
    colour: str = "image"                   # the Gaussians' own colours, or their displacement amplitude (with a
    #                                         scale bar)
    size_px: tuple[int, int] = (640, 480)   # image width and height in px

    def __post_init__(self) -> None:
        check_fields(self, {"alpha": maybe(Range(at_least=ALPHA_RANGE[0], at_most=ALPHA_RANGE[1])),
                            "n_frames": Range(at_least=1, at_most=MAX_EXPORT_FRAMES, integer=True),
                            "fps": PLAYBACK_FPS, "mode": maybe(Range(at_least=1, at_most=10_000, integer=True)),
                            "ods": maybe(Range(at_least=1, at_most=10_000, integer=True)),
                            "time_s": maybe(Range(at_least=-MAX_DURATION_S, at_most=MAX_DURATION_S)),
                            "camera": maybe(Range(at_least=0, at_most=10_000, integer=True)),
                            "size_px": Range(at_least=8, at_most=MAX_VIEW_PX, integer=True)})
        check_choice("ViewSettings.colour", self.colour, COLOURS)
        if sum(x is not None and x is not False for x in (self.mode, self.ods, self.motion or None)) > 1:
            raise InputError("ViewSettings.mode", "give one of mode K, ods K or motion (--mode K, --ods K, --motion)")


def view_state(data: Any, s: ViewSettings) -> Any:
    """The viewer's state for `s` on a capture's `data` (viewer.load_viewer), checked against what it has: the
    mode or ODS line by its number, the motion only with a reconstruction, the camera by its index."""
    state = default_state(data, alpha=s.alpha, structure_only=s.structure_only, colour=s.colour,
                          width_px=s.size_px[0], height_px=s.size_px[1], surface=s.surface)
    if s.mode is not None or s.ods is not None:
        kind, field, number = ("mode", "mode", s.mode) if s.ods is None else ("ods", "ods", s.ods)
        index = [k for k, m in enumerate(data.modes) if m.kind == kind]
        if not 1 <= number <= len(index):
            raise InputError(f"ViewSettings.{field}", f"expected {'a mode' if kind == 'mode' else 'an ODS line'} "
                                                      f"from 1 to {len(index)}, got {number}")
        state = replace(state, mode=index[number - 1], time_s=start_time_s(data, index[number - 1]))
    elif s.motion:
        if data.scene is None:
            raise InputError("ViewSettings.motion", "no reconstruction: only the modes can be shown (--mode K)")
        state = replace(state, mode=None, time_s=start_time_s(data, None))
    if s.surface and data.surface is None:
        raise InputError("ViewSettings.surface", "the analysis has no video surface to draw (no reconstruction, or "
                                                 "its surface points span no surface): leave out --surface")
    if s.alpha is None:
        state = replace(state, alpha=visible_alpha(data, state))
    if s.time_s is not None:
        state = replace(state, time_s=s.time_s)
    if s.camera is not None:
        if not s.camera < len(data.cameras):
            raise InputError("ViewSettings.camera", f"expected a capture camera from 0 to {len(data.cameras) - 1}, "
                                                    f"got {s.camera}")
        state = replace(state, snap=s.camera)
    return state


__all__ = ["COLOURS", "RenderSettings", "ViewSettings", "view_state"]
