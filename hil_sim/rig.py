"""The simulated impact-test rig: one structure, one hammer, one camera and every sensor on one time base.

Four rigs are built in: the arm (the default), the plate, the frame and the mast (`make_rig("plate")`, ...),
each with its own sensors and hammer point (`rig_config`, `HAMMER`).

Rig time is physical time in seconds, zero at the DAQ's START (its sample 0). Everything else is
placed on it:

- the DAQ's sample s is at rig time s / f_true, where f_true is the DAQ's true (possibly drifting) rate;
- a CAN node's sample s is at can_t0_s[node] + s / f_node_true;
- the camera's frames lie on its own clock ticks (`SimCamera`, which may be offset and drift).

The rig is the `SampleSource` of the simulated DAQ (hammer force through the load cell's sensitivity,
accelerometers through theirs, the camera's exposure strobe) and the `AccelSource` of the CAN nodes.
Its camera's external trigger is wired to the hammer: the first time the force rises through
`trigger_level_n` while the camera waits for a trigger, it fires, as a trigger box on the load cell does.

A take is scripted before the DAQ starts: mount and arm the camera, schedule the hits, then acquire.
`truth()` then returns everything the take really was, and `TakeTruth.save` writes it beside the take.
"""
from __future__ import annotations

import dataclasses
import itertools
import logging
import threading
from collections.abc import Sequence
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from odsplat.acquisition import CANNode, DAQChannel
from odsplat.spine.atomic import atomic_open
from odsplat.spine.errors import InputError, OdsplatError
from odsplat.spine.manifest import CameraInfo, Intrinsics

from .camera import SimCamera, SimCameraConfig
from .daq import register_source
from .render import PinholeCamera
from .scene import RigScene, SceneSettings, build_scene
from .structure import STRUCTURES, Hammer, Impact, PlateGeometry, check_unit_vector, make_structure

log = logging.getLogger(__name__)

G_M_S2 = 9.80665
_RIG_SERIAL = itertools.count(1)
TRUTH_SUFFIX = ".truth.npz"


@dataclass(frozen=True)
class Accelerometer:
    """A uniaxial IEPE accelerometer wired to a DAQ input: measures the acceleration along `direction`."""

    name: str
    point_m: tuple[float, float, float]
    direction: tuple[float, float, float]
    sensitivity_v_per_m_s2: float = 0.100 / G_M_S2  # 100 mV/g
    noise_m_s2: float = 0.0  # rms of white sensor noise

    def __post_init__(self) -> None:
        check_unit_vector(self.direction, f"Accelerometer {self.name!r}.direction")


@dataclass(frozen=True)
class CANNodeMount:
    """A triaxial CAN accelerometer node: rows of `axes` are its x, y, z axes in world coordinates."""

    node_id: int
    point_m: tuple[float, float, float]
    axes: tuple[tuple[float, float, float], ...] = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
    noise_m_s2: float = 0.0
    t0_s: float = 0.0  # rig time of the node's sample 0 (nodes start on their own START command)

    def __post_init__(self) -> None:
        a = np.asarray(self.axes, float)
        if a.shape != (3, 3) or not np.allclose(a @ a.T, np.eye(3), atol=1e-6):
            raise InputError(f"CAN node {self.node_id}.axes", f"expected 3 orthonormal rows; got {self.axes}")


DEFAULT_HAMMER_POINT = (0.46, 0.03, 0.60)  # the arm tip's top edge: an oblique hit there excites every mode
DEFAULT_HAMMER_DIRECTION = (-0.25, -0.45, -0.86)

DEFAULT_ACCELEROMETERS = (
    Accelerometer("acc_tip_z", (0.43, 0.0, 0.60), (0.0, 0.0, 1.0)),
    Accelerometer("acc_tip_y", (0.40, 0.03, 0.57), (0.0, 1.0, 0.0)),
    Accelerometer("acc_col_x", (0.045, 0.0, 0.40), (1.0, 0.0, 0.0)),
    Accelerometer("acc_col_y", (0.0, -0.045, 0.45), (0.0, -1.0, 0.0)),
)
DEFAULT_CAN_NODES = (
    CANNodeMount(1, (0.25, 0.0, 0.60)),
    CANNodeMount(2, (0.0, 0.045, 0.50), axes=((0.0, 1.0, 0.0), (-1.0, 0.0, 0.0), (0.0, 0.0, 1.0))),
)


_PLATE = PlateGeometry()
# Vertical accelerometers on the plate's top where every one of its six modes moves (none on a nodal line).
PLATE_ACCELEROMETERS = (
    Accelerometer("acc_a_z", _PLATE.point(0.80, 0.65), (0.0, 0.0, 1.0)),
    Accelerometer("acc_b_z", _PLATE.point(0.40, 0.85), (0.0, 0.0, 1.0)),
    Accelerometer("acc_c_z", _PLATE.point(0.62, 0.38), (0.0, 0.0, 1.0)),
    Accelerometer("acc_d_z", _PLATE.point(0.13, 0.20), (0.0, 0.0, 1.0)),
)
PLATE_CAN_NODES = (CANNodeMount(1, _PLATE.point(0.30, 0.60)), CANNodeMount(2, _PLATE.point(0.70, 0.30)))

# The frame (hil_sim.beams.frame_geometry; beam top at z = 0.61, stub tip at y = 0.15): every one of its five modes
# moves one of these at least 43 % of its largest motion anywhere (tests/hil_sim/test_beams.py measures it).
FRAME_ACCELEROMETERS = (
    Accelerometer("acc_beam_z", (0.20, 0.0, 0.61), (0.0, 0.0, 1.0)),         # the beam's top, mid-span
    Accelerometer("acc_stub_x", (0.215, 0.13, 0.60), (1.0, 0.0, 0.0)),      # the stub's side near its tip
    Accelerometer("acc_top_y", (-0.02, -0.025, 0.60), (0.0, -1.0, 0.0)),    # the beam's side over column 0
    Accelerometer("acc_col_y", (0.42, 0.0125, 0.34), (0.0, 1.0, 0.0)),      # column 1's side, half-way up
)
FRAME_CAN_NODES = (CANNodeMount(1, (0.38, 0.0, 0.61)), CANNodeMount(2, (-0.0325, 0.0, 0.35)))
# The mast (hil_sim.beams.mast_geometry; 19.4 x 20 mm, x = 0.2, z = 0.09 to 0.72): x and y at its tip, x and y
# below the second bending pair's node, so each mode moves one of them at least 92 % of its tip motion.
MAST_ACCELEROMETERS = (
    Accelerometer("acc_tip_x", (0.2097, 0.0, 0.71), (1.0, 0.0, 0.0)),
    Accelerometer("acc_tip_y", (0.2, -0.01, 0.71), (0.0, -1.0, 0.0)),
    Accelerometer("acc_mid_x", (0.1903, 0.0, 0.40), (-1.0, 0.0, 0.0)),
    Accelerometer("acc_mid_y", (0.2, 0.01, 0.45), (0.0, 1.0, 0.0)),
)
MAST_CAN_NODES = (CANNodeMount(1, (0.2097, 0.0, 0.30)), CANNodeMount(2, (0.2, -0.01, 0.50)))
_SENSORS = {"plate": (PLATE_ACCELEROMETERS, PLATE_CAN_NODES), "frame": (FRAME_ACCELEROMETERS, FRAME_CAN_NODES),
            "mast": (MAST_ACCELEROMETERS, MAST_CAN_NODES)}
# Each rig's hammer point and direction: the plate is hit straight down off its nodal lines, the frame obliquely on
# its stub's tip (every mode gets at least 41 % of the best one's participation), the mast obliquely on an edge at
# z = 0.45 m, below the second pair's node (at least 54 %).
HAMMER = {"arm": (DEFAULT_HAMMER_POINT, DEFAULT_HAMMER_DIRECTION),
          "plate": (_PLATE.point(0.22, 0.28), (0.0, 0.0, -1.0)),
          "frame": ((0.215, 0.15, 0.605), (-0.60, -0.65, -0.45)),
          "mast": ((0.2097, -0.01, 0.45), (-0.62, 0.74, -0.26))}


@dataclass(frozen=True)
class RigConfig:
    """How the rig is instrumented. DAQ inputs are, in order: force, the accelerometers, the camera strobe."""

    force_channel: str = "force"
    force_sensitivity_v_per_n: float = 2.25e-3  # a typical impact hammer's load cell
    force_noise_n: float = 0.0
    accelerometers: tuple[Accelerometer, ...] = DEFAULT_ACCELEROMETERS
    ttl_channel: str | None = "cam_ttl"
    can_nodes: tuple[CANNodeMount, ...] = DEFAULT_CAN_NODES
    trigger_level_n: float = 10.0  # the camera's external trigger fires when the force rises through this
    daq_drift_ppm: float = 0.0  # the DAQ's true rate is nominal * (1 + ppm 1e-6); used to state DAQ time in the truth
    n_surface_points: int = 256  # structure points whose displacement the truth records
    seed: int = 0

    def __post_init__(self) -> None:
        names = [self.force_channel, *(a.name for a in self.accelerometers)]
        if self.ttl_channel:
            names.append(self.ttl_channel)
        dupes = sorted({n for n in names if names.count(n) > 1})
        if dupes:
            raise InputError("RigConfig", f"DAQ channel names must be distinct; repeated: {dupes}")
        ids = [n.node_id for n in self.can_nodes]
        if len(set(ids)) != len(ids):
            raise InputError("RigConfig.can_nodes", f"node ids must be distinct; got {ids}")
        if self.trigger_level_n <= 0:
            raise InputError("RigConfig.trigger_level_n", f"must be positive, got {self.trigger_level_n}")


def rig_config(structure: str = "arm", **kw) -> RigConfig:
    """The instrumentation of a built-in rig: its accelerometers and CAN nodes; other RigConfig fields by keyword."""
    if structure not in STRUCTURES:
        raise InputError("structure", f"expected one of {', '.join(STRUCTURES)}; got {structure!r}")
    if structure in _SENSORS:
        accelerometers, nodes = _SENSORS[structure]
        kw = {"accelerometers": accelerometers, "can_nodes": nodes, **kw}
    return RigConfig(**kw)


def make_rig(structure: str = "arm", scene: SceneSettings | None = None, *, seed: int = 0) -> SimRig:
    """A built-in rig by its structure's name ("arm", "plate", "frame" or "mast"), with its sensors and hammer, in a
    scene."""
    config = rig_config(structure, seed=seed)
    return SimRig(build_scene(make_structure(structure), scene), config)


class SimRig:
    """The rig. Use it as the DAQ's source (`register`, then `simdaq://NAME`) and the CAN nodes' source."""

    def __init__(self, scene: RigScene | None = None, config: RigConfig | None = None, hammer: Hammer | None = None):
        self.scene = scene or build_scene()
        self.structure = self.scene.structure
        name = getattr(self.structure, "name", "arm")
        self.config = config or rig_config(name if name in STRUCTURES else "arm")
        point, direction = HAMMER.get(name, HAMMER["arm"])
        self.hammer = hammer or Hammer(point, direction, seed=self.config.seed)
        self.impacts: list[Impact] = []
        self.camera: SimCamera | None = None
        self._nodes = {n.node_id: n for n in self.config.can_nodes}
        acc = self.config.accelerometers
        self._acc_points = np.array([a.point_m for a in acc], float).reshape(-1, 3)
        self._acc_dirs = np.array([a.direction for a in acc], float).reshape(-1, 3)
        self._acc_dirs /= np.linalg.norm(self._acc_dirs, axis=1, keepdims=True) if len(acc) else 1.0
        self._acc_phi = (self.structure.mode_shapes(self._acc_points) if len(acc)
                         else np.zeros((0, self.structure.n_modes, 3)))
        self._node_phi = {i: self.structure.mode_shapes(np.asarray(n.point_m, float)[None])[0]
                          for i, n in self._nodes.items()}
        rng = np.random.default_rng(self.config.seed)
        movers = self.scene.structure_vertices()
        pick = np.sort(rng.choice(len(movers), size=min(self.config.n_surface_points, len(movers)), replace=False))
        self.surface_points_m = self.scene.rest_m[movers[pick]]
        self._surface_phi = self.scene.shapes[movers[pick]]
        self.daq_true_rate_hz: float | None = None  # the rate the DAQ really sampled at, seen on its requests
        self._horizon = 0  # one past the newest DAQ sample produced
        self._lock = threading.RLock()  # the DAQ thread reads the script while the session writes it
        self._take = 0
        self.name = f"rig{next(_RIG_SERIAL)}"

    # ------------------------------------------------------------------------------ the take's script

    def new_take(self) -> None:
        """The structure at rest again, no hits scheduled, the camera disarmed (kept where it is).

        Call it before the DAQ's START: rig time restarts at 0 with the device's sample counter."""
        with self._lock:
            self.impacts = []
            self.daq_true_rate_hz = None
            self._horizon = 0
            self._take += 1
            if self.camera is not None:
                self.camera.stop()
                self.camera.reseed(self._take)

    def mount_camera(self, camera: PinholeCamera, config: SimCameraConfig | None = None, **camera_kw) -> SimCamera:
        """Put the camera in the rig at a pose; keyword arguments go to `SimCamera`. Its clock is the rig's."""
        camera_kw.setdefault("seed", self._take)
        camera_kw.setdefault("clock", self.now_s)
        camera_kw.setdefault("lock", self._lock)
        self.camera = SimCamera(self.scene, camera, self.motion, config, **camera_kw)
        return self.camera

    def place_camera(self, camera: PinholeCamera) -> None:
        """Move the mounted camera to another pose (the engineer carrying it to the next view)."""
        if self.camera is None:
            raise OdsplatError("SimRig.place_camera: no camera mounted")
        self.camera.camera = camera

    def now_s(self) -> float:
        """Rig time of the newest sample the DAQ has produced: everything after it may still be changed.

        A hit scheduled at or after now_s() is consistent with every sample already sent."""
        with self._lock:
            return self._horizon / self.daq_true_rate_hz if self.daq_true_rate_hz else 0.0

    def hit(self, time_s: float | None = None, *, delay_s: float = 0.0, double: bool | None = None) -> list[Impact]:
        """The hammer strikes at rig time `time_s`, or `delay_s` after now (with its scatter, and maybe a bounce)."""
        with self._lock:
            t = self.now_s() + delay_s if time_s is None else time_s
            return self.add_impacts(self.hammer.hit(t, double=double))

    def strike(self, impacts: Sequence[Impact], *, delay_s: float = 0.0) -> list[Impact]:
        """Schedule impacts whose `time_s` counts from the strike: shifted to now_s() + delay_s under the rig's lock,
        so no DAQ sample can be produced between reading the time and scheduling (the automatic hammer's way)."""
        with self._lock:
            t0 = self.now_s() + delay_s
            return self.add_impacts([dataclasses.replace(i, time_s=t0 + i.time_s) for i in impacts])

    def add_impacts(self, impacts: Sequence[Impact]) -> list[Impact]:
        """Schedule exact impacts; a camera waiting for its external trigger fires on the first level crossing."""
        with self._lock:
            if impacts and min(i.time_s for i in impacts) < self.now_s():
                log.warning("impact at %.6f s scheduled before the DAQ's newest sample (%.6f s): samples already sent "
                            "do not show it", min(i.time_s for i in impacts), self.now_s())
            self.impacts.extend(impacts)
            self.impacts.sort(key=lambda imp: imp.time_s)
            cam = self.camera
            if cam is not None and cam.waiting_for_trigger:
                edge = self.trigger_edge_s()
                if edge is not None:
                    cam.trigger_at(edge)
                    log.info("camera triggered by the hammer at rig time %.6f s", edge)
        return list(impacts)

    def trigger_edge_s(self) -> float | None:
        """Rig time at which the force first rises through the trigger level (exact), or None if it never does."""
        level = self.config.trigger_level_n
        edges = []
        for imp in self.impacts:
            if imp.peak_n > level:
                edges.append(imp.time_s + imp.duration_s / np.pi * np.arcsin(level / imp.peak_n))
        # Pulses that overlap could sum through the level where neither does alone; check on a fine grid.
        if len(self.impacts) > 1:
            t0 = self.impacts[0].time_s
            t1 = max(i.time_s + i.duration_s for i in self.impacts)
            t = np.linspace(t0, t1, 20_001)
            over = np.flatnonzero(self.force_n(t) > level)
            if over.size:
                edges.append(float(t[over[0]]))
        return min(edges) if edges else None

    # ------------------------------------------------------------------------------ physics

    def motion(self, t_s: np.ndarray) -> np.ndarray:
        """Modal coordinates (n_modes, T) at rig times t_s."""
        return self.structure.modal_response(self.impacts, np.asarray(t_s, float)).q

    def force_n(self, t_s: np.ndarray) -> np.ndarray:
        """The hammer force (N) at rig times t_s: the sum of the scheduled pulses."""
        t = np.asarray(t_s, float)
        out = np.zeros_like(t)
        for imp in self.impacts:
            out = out + imp.force(t)
        return out

    # ------------------------------------------------------------------------------ DAQ source

    @property
    def channel_names(self) -> tuple[str, ...]:
        c = self.config
        names = (c.force_channel, *(a.name for a in c.accelerometers))
        return names + ((c.ttl_channel,) if c.ttl_channel else ())

    def volts(self, start_sample: int, n: int, sample_rate_hz: float) -> np.ndarray:
        """The DAQ inputs, in volts, for samples start_sample.. taken at the DAQ's true rate."""
        with self._lock:
            self.daq_true_rate_hz = float(sample_rate_hz)
            self._horizon = max(self._horizon, start_sample + n)
            return self._volts(start_sample, n, sample_rate_hz)

    def _volts(self, start_sample: int, n: int, sample_rate_hz: float) -> np.ndarray:
        c = self.config
        t = (start_sample + np.arange(n)) / sample_rate_hz
        rng = np.random.default_rng((c.seed, self._take, start_sample))
        force = self.force_n(t)
        if c.force_noise_n:
            force = force + c.force_noise_n * rng.standard_normal(n)
        rows = [force * c.force_sensitivity_v_per_n]
        if c.accelerometers:
            acc = self.accelerations_m_s2(t)
            for k, a in enumerate(c.accelerometers):
                noisy = acc[k] + (a.noise_m_s2 * rng.standard_normal(n) if a.noise_m_s2 else 0.0)
                rows.append(noisy * a.sensitivity_v_per_m_s2)
        if c.ttl_channel:
            rows.append(self.camera.ttl(t) if self.camera is not None else np.zeros(n))
        return np.vstack(rows)

    def accelerations_m_s2(self, t_s: np.ndarray) -> np.ndarray:
        """(S, T) what the DAQ accelerometers feel along their axes at the rig's times t_s, without their noise."""
        qdd = self.structure.modal_response(self.impacts, np.asarray(t_s, float)).qdd
        return np.einsum("skc,sc,kt->st", self._acc_phi, self._acc_dirs, qdd)

    def register(self, name: str | None = None) -> str:
        """Make `simdaq://NAME` acquire from this rig; returns a URL prefix (add `?fs=...` and faults).

        The default name is unique to this rig (`rig1`, `rig2`, ...); `simdaq://rig` stays the default rig."""
        name = name or self.name
        register_source(name, self)
        return f"simdaq://{name}"

    def daq_url(self, name: str | None = None, *, fs_max_hz: float = 51_200.0, **options) -> str:
        """Register and build the URL, with the DAQ drift of the config and any further URL options."""
        query = {"fs": f"{fs_max_hz:g}", **{k: str(v) for k, v in options.items()}}
        if self.config.daq_drift_ppm:
            query["drift_ppm"] = repr(self.config.daq_drift_ppm)
        return self.register(name) + "?" + "&".join(f"{k}={v}" for k, v in query.items())

    # ------------------------------------------------------------------------------ CAN source

    def acceleration(self, node_id: int, start_sample: int, n: int, sample_rate_hz: float) -> np.ndarray:
        """(n, 3) m/s^2 in the node's axes."""
        mount = self._mount(node_id)
        t = mount.t0_s + (start_sample + np.arange(n)) / sample_rate_hz
        with self._lock:
            qdd = self.structure.modal_response(self.impacts, t).qdd
        world = np.einsum("kc,kt->tc", self._node_phi[node_id], qdd)
        local = world @ np.asarray(mount.axes, float).T
        if mount.noise_m_s2:
            rng = np.random.default_rng((self.config.seed, self._take, node_id, start_sample))
            local = local + mount.noise_m_s2 * rng.standard_normal(local.shape)
        return local

    def samples_available(self, node_id: int, sample_rate_hz: float) -> int:
        """How many of the node's samples lie before now_s(): a node paced by the rig takes no more, so a hit
        scheduled at or after now_s() shows in every later sample, as with the DAQ's."""
        t0 = self._mount(node_id).t0_s
        return max(0, int(np.ceil((self.now_s() - t0) * sample_rate_hz)))

    def _mount(self, node_id: int) -> CANNodeMount:
        try:
            return self._nodes[node_id]
        except KeyError:
            raise InputError(f"CAN node {node_id}", f"not mounted on the rig; mounted: {sorted(self._nodes)}") from None

    # ------------------------------------------------------------------------------ metadata

    def can_nodes(self) -> tuple[CANNode, ...]:
        """The CAN nodes as the session knows them: where they sit, their axes, and their sample 0 on the DAQ's
        time base (the mount's t0_s: rig time is the DAQ's, less its drift)."""
        return tuple(CANNode(n.node_id, tuple(n.point_m), tuple(tuple(a) for a in n.axes), n.t0_s)
                     for n in self.config.can_nodes)

    def daq_channels(self, *, force_range_v: float = 10.0, acc_range_v: float = 10.0) -> tuple[DAQChannel, ...]:
        """The DAQ inputs as a driver configures them: input numbers, sensitivities, ranges, sensor places."""
        c = self.config
        out = [DAQChannel(c.force_channel, 0, "force", c.force_sensitivity_v_per_n, force_range_v,
                          tuple(self.hammer.point_m), tuple(self.hammer.direction))]
        out += [DAQChannel(a.name, 1 + k, "acceleration", a.sensitivity_v_per_m_s2, acc_range_v, a.point_m, a.direction)
                for k, a in enumerate(c.accelerometers)]
        if c.ttl_channel:
            out.append(DAQChannel(c.ttl_channel, len(out), "ttl", 1.0, 10.0))
        return tuple(out)

    # ------------------------------------------------------------------------------ ground truth

    def truth(self, n_daq_samples: int, *, daq_rate_hz: float | None = None) -> TakeTruth:
        """Everything the take really was, for DAQ samples 0..n_daq_samples-1 and the camera's recording.

        `daq_rate_hz` is the DAQ's true rate; by default the one it sampled at."""
        rate = daq_rate_hz or self.daq_true_rate_hz
        if rate is None:
            raise OdsplatError("SimRig.truth: the DAQ never sampled this take; give daq_rate_hz")
        if not self.impacts:
            raise OdsplatError("SimRig.truth: no hit in this take")
        c, st = self.config, self.structure
        nominal = rate / (1.0 + 1e-6 * c.daq_drift_ppm)
        t_daq = np.arange(n_daq_samples) / rate
        mr = st.modal_response(self.impacts, t_daq)
        imp_t = np.array([i.time_s for i in self.impacts])
        names = [a.name for a in c.accelerometers]
        node_points = np.array([n.point_m for n in c.can_nodes], float).reshape(-1, 3)
        sensor_points = np.concatenate([self._acc_points, node_points])
        sensor_phi = st.mode_shapes(sensor_points) if len(sensor_points) else np.zeros((0, st.n_modes, 3))
        kw = dict(
            impact_time_s=imp_t,
            impact_daq_sample=imp_t * rate,
            impact_daq_time_s=imp_t * rate / nominal,
            impact_peak_n=np.array([i.peak_n for i in self.impacts]),
            impact_duration_s=np.array([i.duration_s for i in self.impacts]),
            impact_point_m=np.array([i.point_m for i in self.impacts], float),
            impact_direction=np.array([i.direction for i in self.impacts], float),
            daq_rate_hz=nominal,
            daq_true_rate_hz=rate,
            force_n=self.force_n(t_daq).astype(np.float32),
            freqs_hz=st.freqs_hz,
            dampings=st.dampings,
            mode_names=np.array([m.name for m in st.modes]),
            structure=getattr(st, "name", "arm"),
            modal_q_daq=mr.q.astype(np.float32),
            modal_qdd_daq=mr.qdd.astype(np.float32),
            sensor_names=np.array(names + [f"node{n.node_id}" for n in c.can_nodes]),
            sensor_points_m=sensor_points,
            sensor_directions=np.concatenate([self._acc_dirs, np.full((len(node_points), 3), np.nan)]),
            sensor_mode_shapes=sensor_phi,
            surface_points_m=self.surface_points_m,
            surface_mode_shapes=self._surface_phi,
            can_t0_s=np.array([n.t0_s for n in c.can_nodes], float),
        )
        cam = self.camera
        if cam is not None and cam.recording is not None:
            rec = cam.recording
            fps = cam.config.fps
            mid = rec.exposure_start_s + 0.5 * cam.config.exposure
            q_frames = st.modal_response(self.impacts, mid).q
            frame_of = (imp_t - rec.trigger_frame_time_s) / cam.period_s  # in camera ticks from frame 0
            pin = cam.camera
            kw.update(
                impact_camera_frame=frame_of,
                impact_camera_time_s=frame_of / fps,
                camera_K=pin.K, camera_R=pin.R, camera_t=pin.t,
                camera_size_px=np.array([pin.width_px, pin.height_px]),
                camera_fps=fps, camera_exposure_s=cam.config.exposure,
                camera_clock_offset_s=cam.clock_offset_s, camera_clock_drift_ppm=cam.clock_drift_ppm,
                trigger_time_s=rec.trigger_time_s, trigger_frame_time_s=rec.trigger_frame_time_s,
                frame_counter=rec.counters, frame_time_s=rec.exposure_start_s, dropped_counters=rec.dropped,
                modal_q_frames=q_frames,
            )
        return TakeTruth(**kw)


class _RigFactory:
    """`simdaq://rig?hit_s=0.1`: a default rig with one hit, for trying the DAQ by hand."""

    def __call__(self, hit_s: str = "0.1", seed: str = "0") -> SimRig:
        rig = SimRig(config=RigConfig(seed=int(seed)))
        rig.hit(float(hit_s))
        return rig


register_source("rig", _RigFactory())


# ---------------------------------------------------------------------------------- the truth file

@dataclass
class TakeTruth:
    """Ground truth of one simulated take (rig time unless named otherwise; see docs/hil_sim.md).

    The impact's fractional DAQ sample and fractional camera frame (ticks from the trigger frame's
    exposure start) are what sync must recover. Camera fields are None when no camera recorded.
    """

    impact_time_s: np.ndarray
    impact_daq_sample: np.ndarray
    impact_daq_time_s: np.ndarray
    impact_peak_n: np.ndarray
    impact_duration_s: np.ndarray
    impact_point_m: np.ndarray
    impact_direction: np.ndarray
    daq_rate_hz: float
    daq_true_rate_hz: float
    force_n: np.ndarray                     # (n_samples,) float32, at DAQ samples 0..n-1
    freqs_hz: np.ndarray
    dampings: np.ndarray
    mode_names: np.ndarray
    modal_q_daq: np.ndarray                 # (n_modes, n_samples) float32 modal displacement at DAQ samples
    modal_qdd_daq: np.ndarray               # (n_modes, n_samples) float32 modal acceleration
    sensor_names: np.ndarray
    sensor_points_m: np.ndarray             # (S, 3): the DAQ accelerometers, then the CAN nodes
    sensor_directions: np.ndarray           # (S, 3); NaN for triaxial nodes
    sensor_mode_shapes: np.ndarray          # (S, n_modes, 3) mass-normalised
    surface_points_m: np.ndarray            # (P, 3) rest positions
    surface_mode_shapes: np.ndarray         # (P, n_modes, 3)
    can_t0_s: np.ndarray
    impact_camera_frame: np.ndarray | None = None
    impact_camera_time_s: np.ndarray | None = None
    camera_K: np.ndarray | None = None
    camera_R: np.ndarray | None = None      # world to camera (OpenCV: x right, y down, z forward)
    camera_t: np.ndarray | None = None
    camera_size_px: np.ndarray | None = None
    camera_fps: float | None = None
    camera_exposure_s: float | None = None
    camera_clock_offset_s: float | None = None
    camera_clock_drift_ppm: float | None = None
    trigger_time_s: float | None = None
    trigger_frame_time_s: float | None = None
    frame_counter: np.ndarray | None = None
    frame_time_s: np.ndarray | None = None  # exposure starts
    dropped_counters: np.ndarray | None = None
    modal_q_frames: np.ndarray | None = None          # (n_modes, n_frames) at mid-exposure
    structure: str | None = None            # the rig's structure: "arm", "plate", ... (None: written before it was)
    format_version: int = 1

    @property
    def has_camera(self) -> bool:
        return self.frame_counter is not None

    @property
    def n_daq_samples(self) -> int:
        return int(self.force_n.shape[0])

    # Displacements are stored as modal coordinates and shapes (exact, and a tenth of the size);
    # these give them in metres, world axes.

    def sensor_displacement_m(self) -> np.ndarray:
        """(n_samples, S, 3) at the DAQ samples."""
        return np.einsum("skc,kt->tsc", self.sensor_mode_shapes, self.modal_q_daq.astype(np.float64))

    def sensor_acceleration_m_s2(self) -> np.ndarray:
        """(n_samples, S, 3) at the DAQ samples."""
        return np.einsum("skc,kt->tsc", self.sensor_mode_shapes, self.modal_qdd_daq.astype(np.float64))

    def surface_displacement_m(self) -> np.ndarray:
        """(n_frames, P, 3) at the recorded frames' mid-exposure times."""
        if not self.has_camera:
            raise OdsplatError("this take's truth has no camera")
        return np.einsum("pkc,kt->tpc", self.surface_mode_shapes, self.modal_q_frames)

    def camera(self) -> PinholeCamera:
        if not self.has_camera:
            raise OdsplatError("this take's truth has no camera")
        w, h = (int(v) for v in self.camera_size_px)
        return PinholeCamera(self.camera_K, self.camera_R, self.camera_t, w, h)

    def camera_info(self) -> CameraInfo:
        pin = self.camera()
        return CameraInfo(model=SimCamera.model, width_px=pin.width_px, height_px=pin.height_px, fps=self.camera_fps,
                          exposure_s=self.camera_exposure_s,
                          intrinsics=Intrinsics.from_matrix(pin.K))

    def save(self, path: str | Path) -> Path:
        """Write atomically (temporary file, fsync, rename): a reader never sees half a truth file."""
        return save_fields(self, path)

    @classmethod
    def load(cls, path: str | Path) -> TakeTruth:
        with open_truth(path) as data:
            version = int(data["format_version"]) if "format_version" in data else None
            if version != 1:
                raise InputError(str(path), f"ground-truth format_version 1 expected, found {version}")
            return cls(**read_fields(cls, data, path))


def save_fields(truth, path: str | Path) -> Path:
    """A ground-truth dataclass's fields (those not None) as one .npz, written atomically (temporary file, fsync,
    rename)."""
    path = Path(path)
    arrays = {f.name: np.asarray(getattr(truth, f.name)) for f in fields(truth) if getattr(truth, f.name) is not None}
    with atomic_open(path, "wb") as fh:
        np.savez_compressed(fh, **arrays)
    return path


def open_truth(path: str | Path):
    """A ground-truth .npz, open (use it in `with`); one line naming the file where it is not one."""
    try:
        return np.load(Path(path), allow_pickle=False)
    except (OSError, ValueError) as e:
        raise InputError(str(path), f"not a readable ground-truth file (.npz): {e}") from None


def read_fields(cls, data, path: str | Path) -> dict:
    """The fields of dataclass `cls` from an open ground-truth .npz (scalars as Python values); one whose default
    is None may be absent, any other is refused with one line when it is missing."""
    kw = {}
    for f in fields(cls):
        if f.name in data:
            value = data[f.name]
            kw[f.name] = value.item() if value.ndim == 0 and value.dtype.kind in "fiuU" else value
        elif f.default is not None or f.name == "format_version":
            raise InputError(str(path), f"ground-truth field {f.name!r} is missing")
    return kw


def truth_path(take_path: str | Path) -> Path:
    """Where a take's ground truth lives: takes/NAME.h5 -> takes/NAME.truth.npz."""
    p = Path(take_path)
    return p.with_name(p.name.removesuffix(".h5").removesuffix(".partial") + TRUTH_SUFFIX)



__all__ = ["Accelerometer", "CANNodeMount", "RigConfig", "SimRig", "TakeTruth", "truth_path", "TRUTH_SUFFIX",
           "DEFAULT_ACCELEROMETERS", "DEFAULT_CAN_NODES", "PLATE_ACCELEROMETERS", "PLATE_CAN_NODES", "HAMMER",
           "FRAME_ACCELEROMETERS", "FRAME_CAN_NODES", "MAST_ACCELEROMETERS", "MAST_CAN_NODES",
           "make_rig", "rig_config"]
