"""Live feedback for the capture session: a text summary always, a pyqtgraph window when a display exists."""
from __future__ import annotations

import logging
import os
from collections.abc import Callable

import numpy as np

from odsplat.spine.manifest import Viewpoint

from .session import TakeOutcome
from .trigger import TriggeredRecord

log = logging.getLogger(__name__)


class TextFeedback:
    """Writes where to put the camera, then each take's verdict, force, accelerations and coverage."""

    def __init__(self, write: Callable[[str], None]):
        self._write = write

    def show_view(self, view: Viewpoint, n_views: int, instructions: str) -> None:
        self._write("\n" + instructions)

    def show_take(self, outcome: TakeOutcome, record: TriggeredRecord | None, coverage: float, plan_map: str) -> None:
        if outcome.qc is not None:
            line = f"{outcome.name}: {outcome.qc.summary()}"
        else:
            line = f"{outcome.name}: REJECTED ({outcome.error})"
        if outcome.pose is not None:
            pose = outcome.pose
            line += f"; camera {pose.angular_error_deg:.1f} deg, {pose.distance_error_m:+.2f} m off the plan"
        self._write(line + f"; coverage {coverage:.0%}")


def display_available() -> bool:
    """A Qt window can be shown: an X or Wayland display, or Qt's offscreen platform (tests)."""
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")
                or os.environ.get("QT_QPA_PLATFORM") == "offscreen")


class PlotFeedback(TextFeedback):
    """The text summary plus a window: the last hit's force and accelerations, and the coverage map."""

    def __init__(self, write: Callable[[str], None], plan: list[Viewpoint]):
        super().__init__(write)
        import pyqtgraph as pg  # only here: importing odsplat never needs Qt

        self._pg = pg
        self.app = pg.mkQApp("odsplat capture")
        self.window = pg.GraphicsLayoutWidget(title="odsplat capture")
        self.window.resize(1000, 600)
        self.force_plot = self.window.addPlot(row=0, col=0, title="force [N]")
        self.accel_plot = self.window.addPlot(row=1, col=0, title="acceleration [m/s^2]")
        self.accel_plot.setXLink(self.force_plot)
        self.accel_plot.setLabel("bottom", "time from trigger [s]")
        self.map_plot = self.window.addPlot(row=0, col=1, rowspan=2, title="coverage (top view)")
        self.map_plot.setAspectLocked(True)
        self._az = np.radians([v.azimuth_deg for v in plan])
        self._r = np.cos(np.radians([v.elevation_deg for v in plan]))
        self._planned = pg.ScatterPlotItem(self._r * np.cos(self._az), self._r * np.sin(self._az), size=10,
                                           brush=None, pen=pg.mkPen("w"))
        self._done = pg.ScatterPlotItem(size=12, brush=pg.mkBrush(0, 200, 0))
        self._current = pg.ScatterPlotItem(size=16, brush=pg.mkBrush(250, 200, 0))
        for item in (self._planned, self._done, self._current):
            self.map_plot.addItem(item)
        self._done_views: set[int] = set()
        self.window.show()
        self.app.processEvents()

    def show_view(self, view: Viewpoint, n_views: int, instructions: str) -> None:
        super().show_view(view, n_views, instructions)
        k = view.index
        self._current.setData([self._r[k] * np.cos(self._az[k])], [self._r[k] * np.sin(self._az[k])])
        self.app.processEvents()

    def show_take(self, outcome: TakeOutcome, record: TriggeredRecord | None, coverage: float, plan_map: str) -> None:
        super().show_take(outcome, record, coverage, plan_map)
        pg = self._pg
        self.force_plot.clear()
        self.accel_plot.clear()
        self.accel_plot.addLegend()
        if record is not None:
            t = (np.arange(record.first_sample, record.stop_sample) - record.trigger_sample) / record.sample_rate_hz
            force_name = "force" if "force" in record.channels else record.channels[0]
            self.force_plot.plot(t, np.nan_to_num(record.channel(force_name)), pen=pg.mkPen("y"))
            accel = list((outcome.qc.accel_peak if outcome.qc else {}).keys())
            for k, name in enumerate(accel):
                self.accel_plot.plot(t, np.nan_to_num(record.channel(name)), pen=pg.intColor(k, max(1, len(accel))),
                                     name=name)
        verdict = "accepted" if outcome.accepted else "rejected"
        self.force_plot.setTitle(f"{outcome.name}: {verdict}; force [N]")
        if outcome.accepted:
            self._done_views.add(outcome.view)
        done = sorted(self._done_views)
        self._done.setData(self._r[done] * np.cos(self._az[done]), self._r[done] * np.sin(self._az[done]))
        self.map_plot.setTitle(f"coverage {coverage:.0%}")
        self.app.processEvents()

    def close(self) -> None:
        self.window.close()
        self.app.processEvents()
