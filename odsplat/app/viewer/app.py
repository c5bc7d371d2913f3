"""The viewer's window (PySide6 + pyqtgraph): the 3D view under the mouse (orbit, pan, zoom, snap to a capture
camera), the controls of what moves, and the linked plots (force and accelerations with a time cursor, the FRFs
with a frequency cursor that picks a mode when clicked, the selected mode at the sensors). Every image comes from
`model.render_view`; this module only holds the widgets and their wiring."""
from __future__ import annotations

import logging
import math
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from odsplat.app.viewer.draw import caption
from odsplat.app.viewer.export import export_video, save_screenshot
from odsplat.app.viewer.load import aligned_frame
from odsplat.app.viewer.model import (
    ALPHA_RANGE,
    COLOUR_MODES,
    ViewerData,
    ViewState,
    best_threads,
    default_state,
    render_view,
    snap_orbit,
    start_time_s,
    visible_alpha,
)

log = logging.getLogger(__name__)

ALPHA_STEPS = 500          # the magnification slider's steps over ALPHA_RANGE, logarithmic
TIME_STEPS = 1000          # the time scrubber's steps over the time range
TICK_MS = 40               # the playback timer
MODE_CYCLE_S = 1.5         # a mode plays one cycle in this many seconds, whatever its frequency (at 1 ms of test per
#                            second, one cycle of 23.5 Hz took 42 s)


def alpha_to_slider(alpha: float) -> int:
    lo, hi = ALPHA_RANGE
    a = float(np.clip(alpha, lo, hi))
    return int(round(ALPHA_STEPS * math.log(a / lo) / math.log(hi / lo)))


def slider_to_alpha(value: int) -> float:
    lo, hi = ALPHA_RANGE
    return float(lo * (hi / lo) ** (value / ALPHA_STEPS))


def _qimage(img: np.ndarray):
    from PySide6 import QtGui

    img = np.ascontiguousarray(img)
    h, w = img.shape[:2]
    if img.ndim == 2:
        q = QtGui.QImage(img.data, w, h, img.strides[0], QtGui.QImage.Format.Format_Grayscale8)
    else:
        q = QtGui.QImage(img.data, w, h, img.strides[0], QtGui.QImage.Format.Format_RGB888)
    return q.copy()      # owns its pixels: the array may go


def _view_widget():
    """A QLabel that shows the render and turns mouse drags into orbit (left), pan (right or middle) and wheel
    into zoom, through the callbacks the window sets. The moves a render would fall behind are summed and applied
    at once when Qt is next idle; on_drag(True/False) says when a drag starts and ends."""
    from PySide6 import QtCore, QtWidgets

    class View3D(QtWidgets.QLabel):
        def __init__(self):
            super().__init__()
            self.setAlignment(QtCore.Qt.AlignmentFlag.AlignCenter)
            self.setMinimumSize(320, 240)
            self.setMouseTracking(True)       # moves arrive however the press came (the tests' too)
            self._last = None
            self._button = None
            self._pending = [0.0, 0.0]
            self._timer = QtCore.QTimer(self)
            self._timer.setSingleShot(True)
            self._timer.setInterval(0)
            self._timer.timeout.connect(self._flush)
            self.on_orbit = lambda dx, dy: None
            self.on_pan = lambda dx, dy: None
            self.on_zoom = lambda factor: None
            self.on_drag = lambda dragging: None

        def mousePressEvent(self, e):
            self._last, self._button = e.position(), e.button()
            self.on_drag(True)

        def mouseMoveEvent(self, e):
            if self._last is None:
                return
            d = e.position() - self._last
            self._last = e.position()
            self._pending[0] += d.x()
            self._pending[1] += d.y()
            self._timer.start()

        def _flush(self):
            dx, dy = self._pending
            self._pending = [0.0, 0.0]
            if self._button == QtCore.Qt.MouseButton.LeftButton:
                self.on_orbit(-0.4 * dx, 0.4 * dy)
            else:
                # the scene follows the mouse: the target moves against it (image y grows downwards)
                self.on_pan(-dx / max(self.width(), 1), dy / max(self.width(), 1))

        def mouseReleaseEvent(self, e):
            self._flush()
            self._last = None
            self.on_drag(False)

        def wheelEvent(self, e):
            self.on_zoom(0.9 ** (e.angleDelta().y() / 120))

    return View3D()


class ViewerWindow:
    """The window over one capture's ViewerData. `state` is what is shown; `image` the last render."""

    def __init__(self, data: ViewerData, state: ViewState | None = None):
        import pyqtgraph as pg
        from PySide6 import QtCore, QtWidgets

        self.data = data
        self.state = state or default_state(data)
        self.image: np.ndarray | None = None
        self.render_s = float("nan")
        self.app = pg.mkQApp("odsplat view")
        self.window = QtWidgets.QMainWindow()
        self.window.setWindowTitle(f"odsplat view: {data.name}")
        self._playing = False
        self._last_tick = None
        self._quiet = False     # while controls are set from the state
        self._dragging = False

        central = QtWidgets.QWidget()
        self.window.setCentralWidget(central)
        top = QtWidgets.QHBoxLayout(central)
        left = QtWidgets.QVBoxLayout()
        top.addLayout(left, 3)
        self._build_views(left)
        self._build_plots(left)
        panel = QtWidgets.QVBoxLayout()
        top.addLayout(panel, 1)
        self._build_motion_controls(panel)
        self._build_shown_controls(panel)
        self._build_camera_controls(panel)
        self._build_export_controls(panel)
        self.status = QtWidgets.QLabel("\n".join(data.notes))
        self.status.setWordWrap(True)
        panel.addWidget(self.status)
        panel.addStretch(1)

        self.timer = QtCore.QTimer()
        self.timer.setInterval(TICK_MS)
        self.timer.timeout.connect(self._tick)
        self.window.resize(1500, 950)
        self.threads: int | None = None     # the renderer's threads, measured when playback first starts
        self._sync_controls()
        self.refresh()

    # ------------------------------------------------------------------ building the window

    def _build_views(self, left) -> None:
        """The 3D view under the mouse, the capture camera's real frame beside it (hidden until asked), the
        caption under them."""
        from PySide6 import QtCore, QtWidgets

        views = QtWidgets.QHBoxLayout()
        left.addLayout(views, 3)
        self.view = _view_widget()
        self.view.on_orbit = lambda dx, dy: self.set_state(orbit=self.state.orbit.rotated(dx, dy), snap=None)
        self.view.on_pan = lambda dx, dy: self.set_state(orbit=self.state.orbit.panned(dx, dy), snap=None)
        self.view.on_zoom = lambda f: self.set_state(orbit=self.state.orbit.zoomed(f))
        self.view.on_drag = self._on_drag
        views.addWidget(self.view, 1)
        self.real = QtWidgets.QLabel()
        self.real.setAlignment(QtCore.Qt.AlignmentFlag.AlignCenter)
        self.real.setMinimumSize(320, 240)
        self.real.setVisible(False)
        views.addWidget(self.real, 1)
        self.caption = QtWidgets.QLabel()
        left.addWidget(self.caption)

    def _build_plots(self, left) -> None:
        """The linked plots: force and accelerations against time, the FRFs, the selected mode at the sensors."""
        import pyqtgraph as pg

        self.plots = pg.GraphicsLayoutWidget()
        left.addWidget(self.plots, 2)
        self.force_plot = self.plots.addPlot(row=0, col=0, title="force (N)")
        self.accel_plot = self.plots.addPlot(row=1, col=0, title="accelerations (m/s²)")
        self.accel_plot.setXLink(self.force_plot)
        self.frf_plot = self.plots.addPlot(row=0, col=1, title="FRF |H1| (m/s²/N): click a peak")
        self.shape_plot = self.plots.addPlot(row=1, col=1, title="mode at the sensors: accelerometers, video")
        self._fill_plots()

    def _build_motion_controls(self, panel) -> None:
        """What moves (the measured motion, a mode or an ODS line), the time and its playback."""
        from PySide6 import QtCore, QtGui, QtWidgets

        self.mode_list = QtWidgets.QListWidget()
        self.mode_list.addItem("measured motion" if self.data.scene is not None
                               else "measured motion (no reconstruction)")
        for m in self.data.modes:
            self.mode_list.addItem(m.label())
            if m.not_judged:           # grey, as in the report: its shape is drawn, not judged
                self.mode_list.item(self.mode_list.count() - 1).setForeground(QtGui.QColor(140, 140, 140))
        self.mode_list.currentRowChanged.connect(self._on_mode_row)
        panel.addWidget(QtWidgets.QLabel("what moves"))
        panel.addWidget(self.mode_list, 2)
        self.mode_label = QtWidgets.QLabel()
        self.mode_label.setWordWrap(True)
        panel.addWidget(self.mode_label)
        self.time_slider = QtWidgets.QSlider(QtCore.Qt.Orientation.Horizontal)
        self.time_slider.setRange(0, TIME_STEPS)
        self.time_slider.valueChanged.connect(self._on_time_slider)
        self.time_label = QtWidgets.QLabel()
        panel.addWidget(self.time_label)
        panel.addWidget(self.time_slider)
        row = QtWidgets.QHBoxLayout()
        self.play_button = QtWidgets.QPushButton("play")
        self.play_button.clicked.connect(self.toggle_play)
        self.loop_box = QtWidgets.QCheckBox("loop")
        self.loop_box.setChecked(True)
        self.speed_box = QtWidgets.QDoubleSpinBox()
        self.speed_box.setRange(0.001, 1000.0)
        self.speed_box.setDecimals(3)
        self.speed_box.setValue(1.0)
        self.speed_box.setSuffix(" ms of test / s")
        row.addWidget(self.play_button)
        row.addWidget(self.loop_box)
        panel.addLayout(row)
        panel.addWidget(self.speed_box)

    def _build_shown_controls(self, panel) -> None:
        """How it is shown: the magnification, structure only, the box (plan view and z range), the colour."""
        import pyqtgraph as pg
        from PySide6 import QtCore, QtWidgets

        self.alpha_label = QtWidgets.QLabel()
        self.alpha_slider = QtWidgets.QSlider(QtCore.Qt.Orientation.Horizontal)
        self.alpha_slider.setRange(0, ALPHA_STEPS)
        self.alpha_slider.valueChanged.connect(lambda v: self.set_state(alpha=slider_to_alpha(v)))
        panel.addWidget(self.alpha_label)
        panel.addWidget(self.alpha_slider)
        self.structure_box = QtWidgets.QCheckBox("structure only")
        self.structure_box.toggled.connect(lambda on: self.set_state(structure_only=on))
        panel.addWidget(self.structure_box)
        self.surface_box = QtWidgets.QCheckBox("the structure as its surface (triangles, as in the report)")
        self.surface_box.setEnabled(self.data.surface is not None)
        self.surface_box.toggled.connect(lambda on: self.set_state(surface=on))
        panel.addWidget(self.surface_box)
        self.use_box = QtWidgets.QCheckBox("only inside the box (drag it below; z from the spin boxes)")
        self.use_box.toggled.connect(lambda on: self._on_box())
        panel.addWidget(self.use_box)
        self.box_plot = pg.PlotWidget(title="plan view (x, y): the box")
        self.box_plot.setAspectLocked(True)
        self.box_plot.setMaximumHeight(200)
        self._fill_box_plot()
        panel.addWidget(self.box_plot)
        zrow = QtWidgets.QHBoxLayout()
        self.z_lo, self.z_hi = QtWidgets.QDoubleSpinBox(), QtWidgets.QDoubleSpinBox()
        for box, v in ((self.z_lo, -1.0), (self.z_hi, 10.0)):
            box.setRange(-100, 100)
            box.setDecimals(3)
            box.setSingleStep(0.01)
            box.setValue(v)
            box.setSuffix(" m")
            box.valueChanged.connect(lambda _v: self._on_box())
            zrow.addWidget(box)
        panel.addLayout(zrow)
        self.colour_combo = QtWidgets.QComboBox()
        self.colour_combo.addItems(["colour: image", "colour: displacement amplitude"])
        self.colour_combo.currentIndexChanged.connect(lambda i: self.set_state(colour=COLOUR_MODES[i]))
        panel.addWidget(self.colour_combo)

    def _build_camera_controls(self, panel) -> None:
        """The camera (free, or a capture camera's), the real frame beside the view, what is drawn over it."""
        from PySide6 import QtWidgets

        self.camera_combo = QtWidgets.QComboBox()
        self.camera_combo.addItem("free camera")
        for k, c in enumerate(self.data.cameras):
            self.camera_combo.addItem(f"capture camera {k}: {c.name}")
        self.camera_combo.activated.connect(lambda i: self.snap(i - 1) if i > 0 else self.set_state(snap=None))
        panel.addWidget(self.camera_combo)
        self.compare_box = QtWidgets.QCheckBox("beside it: the capture camera's real frame")
        self.compare_box.toggled.connect(lambda on: (self.real.setVisible(on), self.refresh()))
        panel.addWidget(self.compare_box)
        self.cameras_box = QtWidgets.QCheckBox("show the capture cameras")
        self.cameras_box.setChecked(self.state.show_cameras)
        self.cameras_box.toggled.connect(lambda on: self.set_state(show_cameras=on))
        panel.addWidget(self.cameras_box)
        self.sensors_box = QtWidgets.QCheckBox("show the sensors")
        self.sensors_box.setChecked(self.state.show_sensors)
        self.sensors_box.toggled.connect(lambda on: self.set_state(show_sensors=on))
        panel.addWidget(self.sensors_box)

    def _build_export_controls(self, panel) -> None:
        """The export's frame count and turntable, and the export and screenshot buttons."""
        from PySide6 import QtWidgets

        row = QtWidgets.QHBoxLayout()
        self.frames_box = QtWidgets.QSpinBox()
        self.frames_box.setRange(1, 10000)
        self.frames_box.setValue(48)
        self.frames_box.setSuffix(" frames")
        self.turntable_box = QtWidgets.QCheckBox("turntable")
        row.addWidget(self.frames_box)
        row.addWidget(self.turntable_box)
        panel.addLayout(row)
        row = QtWidgets.QHBoxLayout()
        export_button = QtWidgets.QPushButton("export mp4/gif…")
        export_button.clicked.connect(self._export_dialog)
        shot_button = QtWidgets.QPushButton("screenshot…")
        shot_button.clicked.connect(self._screenshot_dialog)
        row.addWidget(export_button)
        row.addWidget(shot_button)
        panel.addLayout(row)

    # ------------------------------------------------------------------ the state

    def set_state(self, **changes) -> None:
        """Changes the state and renders the view again (controls set programmatically call it once)."""
        if self._quiet:
            return
        self.state = replace(self.state, **changes)
        self._sync_controls()
        self.refresh()

    def select_mode(self, index: int | None) -> None:
        """index in data.modes, or None for the measured motion: shown where it stands furthest from rest, at the
        magnification that makes it visible (model.visible_alpha; the slider changes it after)."""
        time_s = start_time_s(self.data, index)
        state = replace(self.state, mode=index, time_s=time_s)
        self.set_state(mode=index, time_s=time_s, alpha=visible_alpha(self.data, state))

    def select_frequency(self, freq_hz: float) -> int | None:
        """Selects the mode nearest freq_hz (as a click on the FRF does); returns its index."""
        k = self.data.mode_nearest(freq_hz)
        if k is not None:
            self.select_mode(k)
        return k

    def snap(self, index: int) -> None:
        """Looks through capture camera `index`; the next orbit starts from there."""
        self.set_state(snap=index, orbit=snap_orbit(self.data, index, self.state.orbit))

    def set_time(self, time_s: float) -> None:
        self.set_state(time_s=float(time_s))

    def _on_drag(self, dragging: bool) -> None:
        """While the mouse drags the camera the view is drawn at half size (a quarter of the pixels), then again
        in full when it lets go."""
        self._dragging = dragging
        if not dragging:
            self.refresh()

    def refresh(self) -> None:
        from PySide6 import QtCore, QtGui

        t0 = time.perf_counter()
        full = (self.state.width_px, self.state.height_px)
        if self._dragging:
            draft = replace(self.state, width_px=max(full[0] // 2, 8), height_px=max(full[1] // 2, 8))
            image = render_view(self.data, draft)
        else:
            image = self.image = render_view(self.data, self.state)
        self.render_s = time.perf_counter() - t0
        pix = QtGui.QPixmap.fromImage(_qimage(image))
        size = self.view.size().boundedTo(QtCore.QSize(*full))          # fitted, never beyond the full size
        if pix.width() != size.width() or pix.height() != size.height():
            pix = pix.scaled(size, QtCore.Qt.AspectRatioMode.KeepAspectRatio,
                             QtCore.Qt.TransformationMode.SmoothTransformation)
        self.view.setPixmap(pix)
        if self.compare_box.isChecked():
            self._show_real()
        self._cursors()

    def _show_real(self) -> None:
        from PySide6 import QtGui

        k = self.state.snap if self.state.snap is not None else 0
        frame = None
        if self.data.cameras and k < len(self.data.cameras):
            t = self.state.time_s if self.state.mode is None else self.data.time_range_s[0]
            frame = aligned_frame(self.data, self.data.cameras[k].name, t)
        if frame is None:
            self.real.setText("no aligned frame for this camera")
        else:
            self.real.setPixmap(QtGui.QPixmap.fromImage(_qimage(frame)))

    # ------------------------------------------------------------------ controls

    def _sync_controls(self) -> None:
        """Puts the controls where the state is, without their signals changing it back."""
        s, d = self.state, self.data
        self._quiet = True
        try:
            self.alpha_slider.setValue(alpha_to_slider(s.alpha))
            self.alpha_label.setText(f"magnification x{s.alpha:.3g} (in 3D, at render time)")
            self.mode_list.setCurrentRow(0 if s.mode is None else s.mode + 1)
            if s.mode is None:
                self.mode_label.setText("measured motion" + ("" if d.scene is not None else
                                                             ": no reconstruction, pick a mode"))
                t0, t1 = d.time_range_s
                self.time_slider.setValue(int(round(TIME_STEPS * (s.time_s - t0) / max(t1 - t0, 1e-12))))
                self.time_label.setText(f"time {1e3 * s.time_s:.3f} ms after the impact")
            else:
                m = d.modes[s.mode]
                self.mode_label.setText(f"{m.label()}; period {1e3 / m.freq_hz:.2f} ms")
                period = 1.0 / m.freq_hz
                self.time_slider.setValue(int(round(TIME_STEPS * ((s.time_s % period) / period))))
                self.time_label.setText(f"phase {360 * ((s.time_s * m.freq_hz) % 1):.0f}° "
                                        f"(animation time {1e3 * s.time_s:.3f} ms)")
            self.structure_box.setChecked(s.structure_only)
            self.surface_box.setChecked(s.surface)
            self.colour_combo.setCurrentIndex(COLOUR_MODES.index(s.colour))
            self.camera_combo.setCurrentIndex(0 if s.snap is None else s.snap + 1)
            self.caption.setText(f"{self._caption()}   render {1e3 * self.render_s:.0f} ms" if
                                 math.isfinite(self.render_s) else self._caption())
        finally:
            self._quiet = False

    def _caption(self) -> str:
        return caption(self.data, self.state)

    def _on_mode_row(self, row: int) -> None:
        if not self._quiet and row >= 0:
            self.select_mode(None if row == 0 else row - 1)

    def _on_time_slider(self, value: int) -> None:
        if self._quiet:
            return
        if self.state.mode is None:
            t0, t1 = self.data.time_range_s
            self.set_time(t0 + (t1 - t0) * value / TIME_STEPS)
        else:
            self.set_time(value / TIME_STEPS / self.data.modes[self.state.mode].freq_hz)

    def _on_box(self) -> None:
        if self._quiet:
            return
        if not self.use_box.isChecked():
            self.set_state(box_m=None)
            return
        pos, size = self.box_roi.pos(), self.box_roi.size()
        lo = (float(pos[0]), float(pos[1]), self.z_lo.value())
        hi = (float(pos[0] + size[0]), float(pos[1] + size[1]), self.z_hi.value())
        self.set_state(box_m=(lo, hi))

    def toggle_play(self) -> None:
        if self.threads is None:        # playback renders many frames: worth a few to pick the faster threads
            self.threads = best_threads(self.data, self.state) if self.data.scene is not None else 1
        self._playing = not self._playing
        self.play_button.setText("pause" if self._playing else "play")
        self._last_tick = time.perf_counter()
        if self._playing:
            self.timer.start()
        else:
            self.timer.stop()

    def advance(self, wall_s: float) -> None:
        """Moves time on by wall_s of playback: a mode by one cycle per MODE_CYCLE_S; the measured motion at the
        chosen speed (ms of test per second), at its end looping or stopping."""
        if self.state.mode is not None:
            f = self.data.modes[self.state.mode].freq_hz
            self.set_time(self.state.time_s + wall_s / (MODE_CYCLE_S * max(f, 1e-9)))
            return
        t = self.state.time_s + 1e-3 * self.speed_box.value() * wall_s
        t0, t1 = self.data.time_range_s
        if t > t1:
            if self.loop_box.isChecked():
                t = t0 + (t - t0) % max(t1 - t0, 1e-12)
            else:
                t = t1
                if self._playing:
                    self.toggle_play()
        self.set_time(t)

    def _tick(self) -> None:
        now = time.perf_counter()
        wall = now - (self._last_tick or now)
        self._last_tick = now
        self.advance(wall)

    # ------------------------------------------------------------------ plots

    def _fill_plots(self) -> None:
        import pyqtgraph as pg

        d = self.data
        if len(d.signal_times_s):
            self.force_plot.plot(1e3 * d.signal_times_s, d.force_n, pen=pg.mkPen("y"))
            self.accel_legend = self.accel_plot.addLegend(offset=(-10, 10), labelTextSize="8pt")
            for k, a in enumerate(d.accel_m_s2):
                self.accel_plot.plot(1e3 * d.signal_times_s, a, pen=pg.intColor(k, max(1, len(d.accel_m_s2))),
                                     name=d.sensors[k].name if k < len(d.sensors) else str(k))
        t0, t1 = d.time_range_s
        self.force_plot.setXRange(1e3 * t0 - 2, 1e3 * t1 + 0.5 * 1e3 * (t1 - t0), padding=0)
        self.force_plot.setLabel("bottom", "time after the impact", "ms")
        self.accel_plot.setLabel("bottom", "time after the impact", "ms")
        self.time_cursor = pg.InfiniteLine(0.0, angle=90, pen=pg.mkPen("c", width=2))
        self.time_cursor_accel = pg.InfiniteLine(0.0, angle=90, pen=pg.mkPen("c", width=2))
        self.force_plot.addItem(self.time_cursor)
        self.accel_plot.addItem(self.time_cursor_accel)
        if len(d.frf_freq_hz):
            f = d.frf_freq_hz
            top = max([m.freq_hz for m in d.modes], default=f[-1])
            band = f <= min(1.3 * top, f[-1])
            self.frf_legend = self.frf_plot.addLegend(offset=(-10, 10), labelTextSize="8pt")
            for k, h in enumerate(d.frf_h1):
                name = d.frf_names[k].removeprefix("H1 ") if k < len(d.frf_names) else str(k)
                self.frf_plot.plot(f[band], np.abs(h[band]), pen=pg.intColor(k, max(1, len(d.frf_h1))), name=name)
            self.frf_plot.setLogMode(x=False, y=True)
        self.frf_plot.setLabel("bottom", "frequency", "Hz")
        self.freq_cursor = pg.InfiniteLine(0.0, angle=90, pen=pg.mkPen("c", width=2))
        self.frf_plot.addItem(self.freq_cursor)
        self.frf_plot.scene().sigMouseClicked.connect(self._on_frf_click)
        self.shape_plot.setLabel("bottom", "sensor")
        ax = self.shape_plot.getAxis("bottom")
        ax.setTicks([[(k, s.name) for k, s in enumerate(d.sensors)]])

    def _on_frf_click(self, event) -> None:
        vb = self.frf_plot.vb
        pos = event.scenePos()
        if not vb.sceneBoundingRect().contains(pos):
            return
        self.select_frequency(float(vb.mapSceneToView(pos).x()))

    def frf_click_position(self, freq_hz: float):
        """Where, in the plot widget's own pixels, a click lands on freq_hz (for the tests)."""
        import pyqtgraph as pg

        vb = self.frf_plot.vb
        (_, _), (y0, y1) = vb.viewRange()
        scene = vb.mapViewToScene(pg.Point(freq_hz, 0.5 * (y0 + y1)))
        return self.plots.mapFromScene(scene)

    def _cursors(self) -> None:
        import pyqtgraph as pg

        s, d = self.state, self.data
        if s.mode is None:
            self.time_cursor.setValue(1e3 * s.time_s)
            self.time_cursor_accel.setValue(1e3 * s.time_s)
        m = d.modes[s.mode] if s.mode is not None else None
        self.freq_cursor.setVisible(m is not None)
        if m is not None:
            self.freq_cursor.setValue(m.freq_hz)
        self.shape_plot.clear()
        if m is None or m.sensors_accel is None:
            return
        x = np.arange(len(m.sensors_accel))
        # each side's shape as signed amplitudes (real part, phase of its largest entry removed), in m/N
        acc = _real_shape(m.sensors_accel)
        self.shape_plot.addItem(pg.BarGraphItem(x=x - 0.18, height=acc, width=0.34, brush="y", name="accelerometers"))
        if m.sensors_video is not None:
            vid = _real_shape(m.sensors_video, ref=m.sensors_accel)
            self.shape_plot.addItem(pg.BarGraphItem(x=x + 0.18, height=vid, width=0.34, brush="c", name="video"))
        self.shape_plot.setTitle(f"{m.title()} at the sensors (m/N): accelerometers (yellow), video (cyan)")

    def _fill_box_plot(self) -> None:
        import pyqtgraph as pg

        d = self.data
        if d.scene is not None:
            p = d.scene.means_m
            pick = np.random.default_rng(0).choice(len(p), size=min(3000, len(p)), replace=False)
            colours = [pg.mkBrush(255, 200, 0) if d.scene.structure[i] else pg.mkBrush(120, 120, 120) for i in pick]
            self.box_plot.addItem(pg.ScatterPlotItem(p[pick, 0], p[pick, 1], size=2, pen=None, brush=colours))
        c, e = d.target_m, 0.25 * d.extent_m
        self.box_roi = pg.RectROI([c[0] - e, c[1] - e], [2 * e, 2 * e], pen=pg.mkPen("c", width=2))
        self.box_roi.sigRegionChangeFinished.connect(lambda _r: self._on_box())
        self.box_plot.addItem(self.box_roi)

    # ------------------------------------------------------------------ export

    def export(self, path: str | Path, n_frames: int | None = None, turntable: bool | None = None) -> Path:
        return export_video(self.data, self.state, path, n_frames=n_frames or self.frames_box.value(),
                            turntable=self.turntable_box.isChecked() if turntable is None else turntable,
                            progress=False)

    def _export_dialog(self) -> None:
        from PySide6 import QtWidgets

        path, _ = QtWidgets.QFileDialog.getSaveFileName(self.window, "export the view", f"{self.data.name}.mp4",
                                                        "video (*.mp4 *.gif)")
        if path:
            self.status.setText(f"wrote {self.export(path)}")

    def _screenshot_dialog(self) -> None:
        from PySide6 import QtWidgets

        path, _ = QtWidgets.QFileDialog.getSaveFileName(self.window, "screenshot", f"{self.data.name}.png",
                                                        "PNG (*.png)")
        if path:
            self.status.setText(f"wrote {save_screenshot(self.data, self.state, path)}")

    def show(self) -> None:
        self.window.show()

    def run(self) -> int:
        self.show()
        return int(self.app.exec())


def _real_shape(shape: np.ndarray, ref: np.ndarray | None = None) -> np.ndarray:
    """A complex shape as signed real amplitudes: rotated so that ref's (or its own) largest entry is real."""
    ref = shape if ref is None else ref
    k = int(np.argmax(np.abs(ref)))
    phase = ref[k] / abs(ref[k]) if abs(ref[k]) > 0 else 1.0
    return np.real(shape / phase)


def run_viewer(data: ViewerData) -> int:
    """Opens the window and runs Qt's event loop until it is closed."""
    return ViewerWindow(data).run()


__all__ = ["ViewerWindow", "alpha_to_slider", "run_viewer", "slider_to_alpha"]
