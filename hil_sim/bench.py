"""The simulated engineer at the simulated rig: a `Bench` for the capture session, with faults on chosen takes.

It carries the camera to each planned view (with a placement error, as a person would), hits the
structure, accepts what QC accepts, and saves each take's ground truth beside it. Faults are injected
by take number (0 = the first take of this run): a double hit, an overload, a dropped packet, a
disconnect mid-record, or dropped camera frames.

With `SimBenchSettings.can_rate_hz` set, the rig's CAN accelerometer nodes run on a python-can `virtual` bus, paced
by the rig's clock, and the session records them into every take.

With `hammer="serial"` or `"can"` the bench has an automatic hammer instead (`hil_sim.hammer`), which the
session fires through the real driver; its faults are a rebound, not ready, stuck and no response.
"""
from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path

import can
import numpy as np

from odsplat.acquisition import (
    AutoHammer,
    AutoHammerSettings,
    CANAccelerometers,
    CANHammerLink,
    CANSetup,
    CaptureSession,
    Feedback,
    HammerTrigger,
    HitQC,
    PlanSettings,
    QCLimits,
    SerialDAQ,
    SerialHammerLink,
    SessionReport,
    SessionSettings,
    TriggeredRecord,
    view_eye_m,
)
from odsplat.spine.errors import InputError
from odsplat.spine.geometry import spherical_eye, viewing_angle_deg
from odsplat.spine.manifest import Viewpoint

from .camera import SimCamera, SimCameraConfig
from .can_nodes import SimAccelNode
from .daq import register_url_handler
from .hammer import HammerFaults, SimAutoHammer, SimHammerCAN, SimHammerSerial, SimHammerSettings
from .render import PinholeCamera
from .rig import SimRig, make_rig, truth_path
from .scene import SceneSettings
from .structure import STRUCTURES

log = logging.getLogger(__name__)

# The automatic hammer's faults (hil_sim.hammer) by the session's name for them.
HAMMER_FAULTS = {"rebound": "rebound", "hammer_not_ready": "not_ready", "hammer_stuck": "stuck",
                 "hammer_no_response": "no_response"}
FAULTS = ("double_hit", "overload", "dropped_packet", "disconnect", "dropped_frames", *HAMMER_FAULTS)


def parse_faults(spec: str) -> dict[int, str]:
    """'3:double_hit,5:disconnect' -> {3: 'double_hit', 5: 'disconnect'} (take numbers of this run)."""
    out: dict[int, str] = {}
    for item in filter(None, (p.strip() for p in spec.split(","))):
        take, _, kind = item.partition(":")
        if not take.strip().isdigit() or kind not in FAULTS:
            raise InputError("--sim-faults",
                             f"expected TAKE:FAULT items with FAULT one of {', '.join(FAULTS)}; got {item!r}")
        out[int(take)] = kind
    return out


@dataclass(frozen=True)
class SimBenchSettings:
    width_px: int = 400  # at 320x240 the 0.12 m floor tags are too small to detect from the lowest views
    height_px: int = 300
    fov_deg: float = 50.0
    camera: SimCameraConfig = SimCameraConfig(fps=2000.0)
    daq_rate_hz: float = 25_600.0
    placement_error_deg: float = 2.0  # how far off the planned view the engineer puts the camera (rms)
    hit_delay_s: float = 0.05         # after the DAQ's newest sample: when the hammer lands
    overload_factor: float = 12.0
    random_clock_phase: bool = True   # camera and DAQ clocks are independent: each take's frames fall anywhere
    force_scatter: float | None = None  # relative rms of the hit force, take to take (None: the rig hammer's own)
    auto_hammer: SimHammerSettings = SimHammerSettings()  # the automatic hammer, when the bench has one
    can_rate_hz: float | None = None  # the rig's CAN nodes, recorded at this rate (None: not wired to the session)
    can_range_m_s2: float = 490.3325  # +-50 g: the arm's node sees about 26 g from the default hit
    seed: int = 0
    structure: str = "arm"            # the rig: "arm", "plate", "frame" or "mast" (hil_sim.structure)
    scene: SceneSettings = SceneSettings()  # tag sizes, the structure's texture

    def __post_init__(self) -> None:
        for name in ("width_px", "height_px"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not 32 <= v <= 8192:
                raise InputError(f"SimBenchSettings.{name}", f"expected whole pixels, 32 to 8192; got {v!r}")
        if not 5.0 <= self.fov_deg <= 150.0:
            raise InputError("SimBenchSettings.fov_deg", f"expected 5 to 150 degrees; got {self.fov_deg!r}")
        if self.structure not in STRUCTURES:
            raise InputError("SimBenchSettings.structure",
                             f"expected one of {', '.join(STRUCTURES)}; got {self.structure!r}")
        if not isinstance(self.scene, SceneSettings):
            raise InputError("SimBenchSettings.scene", f"expected a SceneSettings; got {type(self.scene).__name__}")
        self.camera.validate()


class SimBench:
    """Implements the session's `Bench` on a `SimRig`."""

    def __init__(self, rig: SimRig | None = None, settings: SimBenchSettings | None = None,
                 faults: Mapping[int, str] | None = None, *, hammer: str | None = None):
        """`hammer`: None for the engineer's manual hammer, or "serial" / "can": an automatic hammer on the rig,
        reached by the real driver over a PTY or a python-can virtual bus (close() the bench when done)."""
        register_url_handler()
        self.settings = settings or SimBenchSettings()
        s = self.settings
        if rig is None:
            rig = make_rig(s.structure, s.scene)
        elif (rig.structure.name, rig.scene.settings) != (s.structure, s.scene):
            raise InputError("SimBench", f"the rig given is the {rig.structure.name!r} in {rig.scene.settings}; the "
                             f"settings ask for the {s.structure!r} in {s.scene} (give one or the other)")
        self.rig = rig
        self.faults = dict(faults or {})
        bad = {k: v for k, v in self.faults.items() if v not in FAULTS}
        if bad:
            raise InputError("SimBench.faults", f"unknown faults {bad}; expected {FAULTS}")
        self.tags = self.rig.scene.tags
        self.channels = self.rig.daq_channels()
        s = self.settings
        start = PinholeCamera.look_at((1.5, 0.0, 1.0), (0.2, 0.0, 0.3), fov_deg=s.fov_deg, width_px=s.width_px,
                                      height_px=s.height_px)
        self.camera: SimCamera = self.rig.mount_camera(start, s.camera, name="simcam")
        self.takes = 0  # takes started in this run
        self._rng = np.random.default_rng(s.seed)
        self._phase_rng = np.random.default_rng((s.seed, 1))
        if s.force_scatter is not None:
            self.rig.hammer.force_scatter = s.force_scatter
        self._daq: SerialDAQ | None = None
        self._fault: str | None = None
        self.true_offsets_deg: dict[int, float] = {}  # view -> how far the camera really was from the plan
        self.hammer: AutoHammer | None = None
        self.hammer_model: SimAutoHammer | None = None  # the simulated device behind it: its ground truth
        self._hammer_device: SimHammerSerial | SimHammerCAN | None = None
        self.can: CANSetup | None = None
        self.can_nodes: list[SimAccelNode] = []  # the simulated nodes: their ground truth (lost samples, ...)
        self._can_buses: list[can.BusABC] = []
        self._can_channel = f"simcan-{self.rig.name}-{id(self)}"
        if s.can_rate_hz is not None:
            self.can = CANSetup(self.rig.can_nodes(), s.can_rate_hz, s.can_range_m_s2)
            for mount in self.rig.config.can_nodes:
                self._can_buses.append(can.Bus(interface="virtual", channel=self._can_channel))
                self.can_nodes.append(SimAccelNode(self._can_buses[-1], mount.node_id, self.rig,
                                                   sample_rate_hz=s.can_rate_hz, range_m_s2=s.can_range_m_s2,
                                                   paced=True))
                self.can_nodes[-1].start()
        if hammer is not None:
            if "overload" in self.faults.values():
                raise InputError("SimBench.faults",
                                 "'overload' is the engineer's hit; the automatic hammer fires its set level")
            # the automatic hammer's double hit is its rebound
            self.faults = {k: "rebound" if v == "double_hit" else v for k, v in self.faults.items()}
            self._open_hammer(hammer)
        elif any(k in HAMMER_FAULTS for k in self.faults.values()):
            raise InputError("SimBench.faults",
                             f"{sorted(HAMMER_FAULTS)} need the automatic hammer (hammer='serial' or 'can')")

    def _open_hammer(self, link: str) -> None:
        # An injected "not ready" lasts a little longer than one fire timeout: that fire expires, the redo fires.
        model = SimAutoHammer(self.rig, replace(self.settings.auto_hammer, seed=self.settings.auto_hammer.seed
                                                + 1000 * self.settings.seed), HammerFaults(not_ready_s=1.5))
        if link == "serial":
            device = SimHammerSerial(model)
            self.hammer = AutoHammer(SerialHammerLink.from_url(device.serve_pty()))
        elif link == "can":
            channel = f"simhammer-{self.rig.name}-{id(self)}"
            device = SimHammerCAN(can.Bus(interface="virtual", channel=channel), model)
            device.start()
            self.hammer = AutoHammer(CANHammerLink(can.Bus(interface="virtual", channel=channel), close_bus=True))
        else:
            raise InputError("SimBench.hammer", f"expected None, 'serial' or 'can'; got {link!r}")
        self.hammer_model, self._hammer_device = model, device

    def open_can(self) -> CANAccelerometers:
        """The CAN driver on its own instance of the nodes' virtual bus (closed by `close`)."""
        if self.can is None:
            raise InputError("SimBench.open_can", "this bench has no CAN nodes (SimBenchSettings.can_rate_hz)")
        self._can_buses.append(can.Bus(interface="virtual", channel=self._can_channel))
        return CANAccelerometers(self._can_buses[-1], [n.node_id for n in self.can.nodes],
                                 sample_rate_hz=self.can.sample_rate_hz, range_m_s2=self.can.range_m_s2,
                                 name=f"CAN virtual:{self._can_channel}")

    def close(self) -> None:
        """Close the automatic hammer's driver and device and the CAN nodes, if any."""
        for node in self.can_nodes:
            node.stop()
        for bus in self._can_buses:
            bus.shutdown()
        self._can_buses = []
        if self.hammer is not None:
            self.hammer.close()
            self.hammer = None
        if isinstance(self._hammer_device, SimHammerSerial):
            self._hammer_device.close()
        elif self._hammer_device is not None:
            self._hammer_device.stop()
        self._hammer_device = None  # hammer_model stays: its ground truth (fires)

    def __enter__(self) -> SimBench:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------------------ Bench

    def open_daq(self) -> SerialDAQ:
        self._fault = self.faults.get(self.takes)
        self.takes += 1
        self.rig.new_take()  # rig time restarts with the DAQ's sample counter
        if self.settings.random_clock_phase:
            self.camera.clock_offset_s = float(self._phase_rng.uniform(0.0, self.camera.period_s))
        self.camera.drop_counters = frozenset({3, 4} if self._fault == "dropped_frames" else ())
        options = {"drop_every": 20} if self._fault == "dropped_packet" else {}
        if self._fault:
            log.warning("sim: injecting %s into take %d", self._fault, self.takes - 1)
        if self._fault in HAMMER_FAULTS:
            self.hammer_model.inject_next(HAMMER_FAULTS[self._fault])
        self._daq = SerialDAQ.from_url(self.rig.daq_url(fs_max_hz=51_200.0, **options), self.channels,
                                       self.settings.daq_rate_hz)
        return self._daq

    def place_camera(self, view: Viewpoint, instructions: str) -> None:
        s = self.settings
        az, el, dist = view.azimuth_deg, view.elevation_deg, view.distance_m
        # A person puts the camera a little off: a random direction on the sphere, about placement_error_deg off.
        d_az, d_el = self._rng.normal(0.0, s.placement_error_deg / np.sqrt(2), 2)
        eye = spherical_eye(az + d_az / max(np.cos(np.radians(el)), 0.2), el + d_el,
                            dist * (1 + 0.01 * self._rng.normal()), view.target_m)
        cam = PinholeCamera.look_at(eye, view.target_m, fov_deg=s.fov_deg, width_px=s.width_px, height_px=s.height_px)
        self.rig.new_take()  # carrying the camera takes a while: the structure is at rest again
        self.rig.place_camera(cam)
        self.true_offsets_deg[view.index] = viewing_angle_deg(view_eye_m(view), eye, view.target_m)

    def hit(self) -> None:
        s = self.settings
        fault = self._fault
        if fault == "overload":
            peak, self.rig.hammer.peak_n = self.rig.hammer.peak_n, self.rig.hammer.peak_n * s.overload_factor
            try:
                self.rig.hit(delay_s=s.hit_delay_s)
            finally:
                self.rig.hammer.peak_n = peak
            return
        impacts = self.rig.hit(delay_s=s.hit_delay_s, double=True if fault == "double_hit" else None)
        if fault == "disconnect" and self._daq is not None:
            device = getattr(self._daq.port, "device", None)
            if device is not None:  # the cable is pulled 0.1 s after the hit, mid-record
                rate = device._true_rate
                device.faults.disconnect_after_samples = int((impacts[0].time_s + 0.1) * rate)

    def decide(self, qc: HitQC, pose) -> bool:
        return qc.accepted

    def retry_view(self, view: Viewpoint, outcomes) -> bool:
        return False  # the simulated engineer moves on; the view is reported missing

    def take_written(self, take_path: Path, record: TriggeredRecord | None) -> None:
        n = record.stop_sample if record is not None else 0
        if n and self.rig.impacts:
            self.rig.truth(n).save(truth_path(take_path))


def simulate_capture(out: str | Path, *, n_views: int = 27, n_frames: int = 100, pretrigger_frames: int = 10,
                     record_s: float = 0.3, pretrigger_s: float = 0.02, settings: SimBenchSettings | None = None,
                     rig: SimRig | None = None, faults: Mapping[int, str] | None = None,
                     max_attempts: int = 5, hammer: AutoHammerSettings | None = None,
                     hammer_link: str = "serial", limits: QCLimits | None = None,
                     feedback: Feedback | None = None, plan: PlanSettings | None = None) -> SessionReport:
    """Record a whole capture on the simulated rig in this process: the guided session with the simulated
    engineer (`odsplat capture --sim --auto` without the command line). For tests, benches and the demo.

    `hammer`: fire the simulated automatic hammer over `hammer_link` at these settings; None: the engineer hits.
    `limits`: the session's QC limits (e.g. `QCLimits(min_tags=0)` where the floor tags are too small to find).
    `feedback`: what the session tells as it goes (e.g. `TextFeedback(print)`, as the command line does); None: the
    log only. `plan`: where the views are (its n_views wins over `n_views`); None: n_views on the default sphere."""

    with SimBench(rig, settings, faults=faults, hammer=hammer_link if hammer is not None else None) as bench:
        session = SessionSettings(name=Path(out).name, plan=plan or PlanSettings(n_views=n_views), n_frames=n_frames,
                                  pretrigger_frames=pretrigger_frames, max_attempts=max_attempts,
                                  trigger=HammerTrigger(pretrigger_s=pretrigger_s, record_s=record_s), hammer=hammer,
                                  limits=limits or QCLimits())
        return CaptureSession(out, session, bench, feedback=feedback).run()
