"""Structures with known modal models, and their exact response to hammer impacts.

Four rigs (world frame: metres, z up, floor at z = 0). The default, `ModalStructure` ("arm"), is a column on
a base with an arm at the top; its motion is the superposition of a few damped modes whose 3D shapes follow
beam kinematics (plane sections stay plane). The second, `PlateStructure` ("plate"), is a steel plate simply
supported on four corner legs, with the closed-form Kirchhoff modes sin(m pi x / a) sin(n pi y / b). The
"frame" (a portal frame) and the "mast" (a slender bar with closely spaced bending pairs) take their modes from
a finite-element model of their members (hil_sim.beams). The response to half-sine hammer pulses is evaluated
in closed form: there is no time-stepping error, so it is the ground truth for every other stage.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from odsplat.spine.errors import InputError

# Euler-Bernoulli cantilever eigenvalues beta_n*L and the sigma_n of their mode functions.
_CANTILEVER = {1: (1.875104069, 0.734095514), 2: (4.694091133, 1.018467319)}


def _cantilever(s: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Clamped-free beam mode n at s in [0, 1], normalised to tip value 1, with its d/ds."""
    beta, sigma = _CANTILEVER[n]
    b = beta * s
    phi = np.cosh(b) - np.cos(b) - sigma * (np.sinh(b) - np.sin(b))
    dphi = beta * (np.sinh(b) + np.sin(b) - sigma * (np.cosh(b) - np.cos(b)))
    tip = np.cosh(beta) - np.cos(beta) - sigma * (np.sinh(beta) - np.sin(beta))
    return phi / tip, dphi / tip


def check_unit_vector(v, what: str) -> None:
    """Raise InputError naming `what` unless v is a 3-vector of length 1."""
    d = np.asarray(v, float)
    if d.shape != (3,) or not np.isclose(np.linalg.norm(d), 1.0, atol=1e-6):
        raise InputError(what, f"expected a unit 3-vector; got {v}")


@dataclass(frozen=True)
class Geometry:
    """Box dimensions of base, column and arm (metres)."""

    base_half_m: float = 0.16
    base_height_m: float = 0.05
    column_half_m: float = 0.045
    column_top_m: float = 0.60
    arm_length_m: float = 0.42
    arm_half_width_m: float = 0.03
    arm_height_m: float = 0.06

    @property
    def column_length_m(self) -> float:
        return self.column_top_m - self.base_height_m

    @property
    def arm_root_x_m(self) -> float:
        return self.column_half_m

    @property
    def arm_z_range_m(self) -> tuple[float, float]:
        return self.column_top_m - self.arm_height_m, self.column_top_m

    @property
    def floor_clear_radius_m(self) -> float:
        """How far from the z axis the structure reaches over the floor: floor tags go 0.22 m beyond."""
        return self.base_half_m

    def tag_mounts(self) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """Where the structure's own tags go, as (centre, image x axis, image y axis): both sides of the column."""
        zc = self.base_height_m + 0.55 * self.column_length_m
        off = self.column_half_m + 5e-4
        ex, ez = np.eye(3)[0], np.eye(3)[2]
        return [(np.array([0.0, -off, zc]), ex, -ez), (np.array([0.0, off, zc]), -ex, -ez)]

    def boxes(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """Each part as (min corner, max corner)."""
        g = self
        z0, z1 = g.arm_z_range_m
        return {
            "base": (np.array([-g.base_half_m, -g.base_half_m, 0.0]),
                     np.array([g.base_half_m, g.base_half_m, g.base_height_m])),
            "column": (np.array([-g.column_half_m, -g.column_half_m, g.base_height_m]),
                       np.array([g.column_half_m, g.column_half_m, g.column_top_m])),
            "arm": (np.array([g.arm_root_x_m, -g.arm_half_width_m, z0]),
                    np.array([g.arm_root_x_m + g.arm_length_m, g.arm_half_width_m, z1])),
        }


@dataclass(frozen=True)
class ModeBase:
    """What every structure's mode has: its natural frequency, damping ratio and a name in words."""

    freq_hz: float
    damping: float
    name: str

    @property
    def omega(self) -> float:
        return 2 * np.pi * self.freq_hz


@dataclass(frozen=True)
class Mode(ModeBase):
    """One mode: natural frequency, damping ratio, and the beam-kinematics parameters of its shape.

    Column bending in x and y (`col_x`, `col_y`, cantilever mode `col_order`), column torsion at the
    top (`twist_rad`), arm bending in z and y (`arm_z`, `arm_y`, cantilever mode `arm_order`), all per
    unit modal coordinate. The shape is divided by sqrt(modal mass) to be mass-normalised.
    """

    col_x: float = 0.0
    col_y: float = 0.0
    col_order: int = 1
    twist_rad: float = 0.0
    arm_z: float = 0.0
    arm_y: float = 0.0
    arm_order: int = 1
    modal_mass_kg: float = 4.0


DEFAULT_MODES = (
    Mode(23.5, 0.010, "column bending x", col_x=1.0, arm_z=-0.05),
    Mode(31.0, 0.008, "column bending y + twist", col_y=1.0, twist_rad=1.2),
    Mode(86.0, 0.015, "arm vertical bending", col_x=-0.12, arm_z=1.0),
    Mode(142.0, 0.012, "arm lateral bending", arm_y=1.0, twist_rad=-0.4),
    Mode(262.0, 0.020, "column second bending x", col_x=1.0, col_order=2, arm_z=0.25, modal_mass_kg=6.0),
    Mode(371.0, 0.025, "arm second vertical bending", arm_z=1.0, arm_order=2, col_x=0.05, modal_mass_kg=1.0),
)


@dataclass(frozen=True)
class Impact:
    """A half-sine hammer pulse: F(t) = peak_n sin(pi (t - time_s) / duration_s) while it lasts."""

    time_s: float
    point_m: tuple[float, float, float]
    direction: tuple[float, float, float]
    peak_n: float = 200.0
    duration_s: float = 1.0e-3

    def __post_init__(self) -> None:
        if not 0.5e-3 <= self.duration_s <= 3e-3:
            raise InputError("Impact.duration_s", f"expected 0.5 to 3 ms; got {self.duration_s * 1e3:.3g} ms")
        check_unit_vector(self.direction, "Impact.direction")

    def force(self, t_s: np.ndarray) -> np.ndarray:
        s = np.asarray(t_s, float) - self.time_s
        on = (s >= 0) & (s <= self.duration_s)
        return np.where(on, self.peak_n * np.sin(np.pi * np.clip(s, 0, self.duration_s) / self.duration_s), 0.0)


@dataclass(frozen=True)
class ModalResponse:
    """Modal coordinates and their derivatives, shape (n_modes, T)."""

    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray


class _ModalModel(ABC):
    """What every structure shares: its modes' frequencies and dampings, and the exact response built on
    `mode_shapes(points_m)` (mass-normalised, (P, n_modes, 3)), which each structure defines."""

    modes: tuple

    @property
    def n_modes(self) -> int:
        return len(self.modes)

    @property
    def freqs_hz(self) -> np.ndarray:
        return np.array([m.freq_hz for m in self.modes])

    @property
    def dampings(self) -> np.ndarray:
        return np.array([m.damping for m in self.modes])

    @abstractmethod
    def mode_shapes(self, points_m: np.ndarray) -> np.ndarray:
        """(P, n_modes, 3) mass-normalised shapes at the points: each structure's own."""

    def participation(self, point_m: Sequence[float], direction: Sequence[float]) -> np.ndarray:
        """phi_r(point) . direction for every mode: how much a force there excites each mode."""
        return self.mode_shapes(np.asarray(point_m, float)[None])[0] @ np.asarray(direction, float)

    def modal_response(self, impacts: Sequence[Impact], t_s: np.ndarray) -> ModalResponse:
        """Exact modal coordinates for the superposed half-sine impacts, at times t_s (any order)."""
        t = np.asarray(t_s, float)
        q = np.zeros((self.n_modes, t.size))
        qd = np.zeros_like(q)
        qdd = np.zeros_like(q)
        for imp in impacts:
            gamma = self.participation(imp.point_m, imp.direction) * imp.peak_n
            for k, m in enumerate(self.modes):
                a, b, c = _half_sine_response(t.ravel() - imp.time_s, imp.duration_s, m.omega, m.damping)
                q[k] += gamma[k] * a
                qd[k] += gamma[k] * b
                qdd[k] += gamma[k] * c
        shape = (self.n_modes, *t.shape)
        return ModalResponse(q.reshape(shape), qd.reshape(shape), qdd.reshape(shape))

    def response(self, points_m: np.ndarray, impacts: Sequence[Impact], t_s: np.ndarray,
                 kind: str = "displacement") -> np.ndarray:
        """3D displacement (m), velocity (m/s) or acceleration (m/s^2) at points: (T, P, 3)."""
        phi = self.mode_shapes(points_m)
        mr = self.modal_response(impacts, t_s)
        coords = {"displacement": mr.q, "velocity": mr.qd, "acceleration": mr.qdd}
        if kind not in coords:
            raise InputError("kind", f"expected displacement, velocity or acceleration; got {kind!r}")
        return np.einsum("pkc,kt->tpc", phi, coords[kind])

    def frf(self, out_point_m, out_dir, in_point_m, in_dir, freqs_hz: np.ndarray,
            kind: str = "receptance") -> np.ndarray:
        """The analytic FRF: sum of modal contributions phi_out phi_in / (w_r^2 - w^2 + 2i zeta_r w_r w)."""
        w = 2 * np.pi * np.asarray(freqs_hz, float)
        po = self.participation(out_point_m, out_dir)
        pi = self.participation(in_point_m, in_dir)
        h = np.zeros(w.shape, complex)
        for k, m in enumerate(self.modes):
            h += po[k] * pi[k] / (m.omega**2 - w**2 + 2j * m.damping * m.omega * w)
        power = {"receptance": 0, "mobility": 1, "accelerance": 2}
        if kind not in power:
            raise InputError("kind", f"expected receptance, mobility or accelerance; got {kind!r}")
        return h * (1j * w) ** power[kind]


@dataclass
class ModalStructure(_ModalModel):
    """The arm rig's geometry and modal model; every response is exact (closed form)."""

    geometry: Geometry = field(default_factory=Geometry)
    modes: tuple[Mode, ...] = DEFAULT_MODES
    name: str = "arm"

    def mode_shapes(self, points_m: np.ndarray) -> np.ndarray:
        """Mass-normalised 3D mode shapes at rest positions: (P, n_modes, 3), in 1/sqrt(kg)."""
        p = np.atleast_2d(np.asarray(points_m, float))
        g = self.geometry
        x, y, z = p[:, 0], p[:, 1], p[:, 2]
        H = g.column_length_m
        s = np.clip((z - g.base_height_m) / H, 0.0, 1.0)
        # Arm coordinate: 0 at the root and everywhere off the arm (the base reaches under it).
        on_arm = z >= g.arm_z_range_m[0] - 1e-9
        r = np.where(on_arm, np.clip((x - g.arm_root_x_m) / g.arm_length_m, 0.0, 1.0), 0.0)
        z_arm = 0.5 * sum(g.arm_z_range_m)
        out = np.zeros((len(p), self.n_modes, 3))
        for k, m in enumerate(self.modes):
            psi, dpsi = _cantilever(s, m.col_order)
            dpsi = dpsi / H  # d/dz
            twist = np.sin(0.5 * np.pi * s) * m.twist_rad
            chi, dchi = _cantilever(r, m.arm_order)
            dchi = dchi / g.arm_length_m  # d/dx
            # Column: bending translation, torsion about z, and the rotation of plane sections.
            ux = m.col_x * psi - twist * y
            uy = m.col_y * psi + twist * x
            uz = -(m.col_x * dpsi * x + m.col_y * dpsi * y)
            # Arm (zero at and behind its root): bending in z and y, with plane sections.
            uz = uz + m.arm_z * chi
            uy = uy + m.arm_y * chi
            ux = ux - m.arm_z * dchi * (z - z_arm) - m.arm_y * dchi * y
            out[:, k] = np.stack([ux, uy, uz], axis=1) / np.sqrt(m.modal_mass_kg)
        return out



@dataclass(frozen=True)
class PlateGeometry:
    """A rectangular plate (length along x, width along y, centred on the z axis) on four corner legs."""

    length_m: float = 0.70
    width_m: float = 0.50
    thickness_m: float = 0.004
    height_m: float = 0.45           # of its mid-plane above the floor
    leg_half_m: float = 0.015

    @property
    def top_m(self) -> float:
        return self.height_m + 0.5 * self.thickness_m

    @property
    def floor_clear_radius_m(self) -> float:
        return 0.5 * float(np.hypot(self.length_m, self.width_m))

    def boxes(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """The plate and its legs as (min corner, max corner); the legs stop 1 mm under the plate."""
        a, b, h = 0.5 * self.length_m, 0.5 * self.width_m, 0.5 * self.thickness_m
        out = {"plate": (np.array([-a, -b, self.height_m - h]), np.array([a, b, self.height_m + h]))}
        leg = self.leg_half_m
        for k, (sx, sy) in enumerate(((-1, -1), (1, -1), (1, 1), (-1, 1))):
            cx, cy = sx * (a - leg), sy * (b - leg)
            out[f"leg{k}"] = (np.array([cx - leg, cy - leg, 0.0]),
                              np.array([cx + leg, cy + leg, self.height_m - h - 1e-3]))
        return out

    def point(self, xi: float, eta: float) -> tuple[float, float, float]:
        """The point of the top surface at fractions (xi, eta) of the length and the width."""
        return ((xi - 0.5) * self.length_m, (eta - 0.5) * self.width_m, self.top_m)

    def tag_mounts(self) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """Two tags on the plate's top, near opposite corners (where it moves least)."""
        ex, ey = np.eye(3)[0], np.eye(3)[1]
        lift = np.array([0.0, 0.0, 5e-4])
        return [(np.asarray(self.point(xi, eta)) + lift, ex, -ey) for xi, eta in ((0.09, 0.86), (0.91, 0.14))]


@dataclass(frozen=True)
class PlateMode(ModeBase):
    """Mode (m, n) of the simply supported plate: m half waves along its length, n across its width."""

    m: int
    n: int
    modal_mass_kg: float


@dataclass(frozen=True)
class PlateMaterial:
    """Steel by default."""

    youngs_modulus_pa: float = 210e9
    density_kg_m3: float = 7850.0
    poisson: float = 0.30


PLATE_DAMPINGS = (0.006, 0.008, 0.010, 0.012, 0.012, 0.015)


def plate_modes(geometry: PlateGeometry, material: PlateMaterial = PlateMaterial(), n_modes: int = 6,
                dampings: Sequence[float] = PLATE_DAMPINGS) -> tuple[PlateMode, ...]:
    """The n_modes lowest modes of a simply supported Kirchhoff plate:
    f_mn = pi / 2 (m^2 / a^2 + n^2 / b^2) sqrt(D / (rho h)), D = E h^3 / (12 (1 - nu^2)); modal mass rho h a b / 4."""
    if len(dampings) < n_modes:
        raise InputError("plate_modes.dampings", f"expected {n_modes} damping ratios, got {len(dampings)}")
    g, mat = geometry, material
    h = g.thickness_m
    d = mat.youngs_modulus_pa * h**3 / (12 * (1 - mat.poisson**2))
    c = np.sqrt(d / (mat.density_kg_m3 * h))
    pairs = sorted(((m, n) for m in range(1, 8) for n in range(1, 8)),
                   key=lambda mn: mn[0]**2 / g.length_m**2 + mn[1]**2 / g.width_m**2)[:n_modes]
    mass = mat.density_kg_m3 * h * g.length_m * g.width_m / 4
    return tuple(PlateMode(float(0.5 * np.pi * (m**2 / g.length_m**2 + n**2 / g.width_m**2) * c), float(z),
                           f"plate ({m},{n})", m, n, float(mass))
                 for (m, n), z in zip(pairs, dampings))


@dataclass
class PlateStructure(_ModalModel):
    """The plate rig: a 0.7 x 0.5 m, 4 mm steel plate simply supported on four legs, its six lowest modes
    (59 to 338 Hz). Kirchhoff kinematics: w(x, y) out of plane, plane sections rotate (u = -z' dw/dx)."""

    geometry: PlateGeometry = field(default_factory=PlateGeometry)
    modes: tuple[PlateMode, ...] = ()
    name: str = "plate"

    def __post_init__(self) -> None:
        if not self.modes:
            self.modes = plate_modes(self.geometry)

    def mode_shapes(self, points_m: np.ndarray) -> np.ndarray:
        """Mass-normalised 3D mode shapes at rest positions: (P, n_modes, 3), in 1/sqrt(kg); zero off the plate."""
        p = np.atleast_2d(np.asarray(points_m, float))
        g = self.geometry
        a, b = g.length_m, g.width_m
        xi = (p[:, 0] + 0.5 * a) / a
        eta = (p[:, 1] + 0.5 * b) / b
        dz = p[:, 2] - g.height_m
        on = ((xi >= -1e-9) & (xi <= 1 + 1e-9) & (eta >= -1e-9) & (eta <= 1 + 1e-9)
              & (np.abs(dz) <= 0.5 * g.thickness_m + 1e-6))
        xi, eta = np.clip(xi, 0.0, 1.0), np.clip(eta, 0.0, 1.0)
        out = np.zeros((len(p), self.n_modes, 3))
        for k, m in enumerate(self.modes):
            sx, sy = np.sin(m.m * np.pi * xi), np.sin(m.n * np.pi * eta)
            dwdx = m.m * np.pi / a * np.cos(m.m * np.pi * xi) * sy
            dwdy = m.n * np.pi / b * sx * np.cos(m.n * np.pi * eta)
            u = np.stack([-dz * dwdx, -dz * dwdy, sx * sy], axis=1)
            out[:, k] = np.where(on[:, None], u, 0.0) / np.sqrt(m.modal_mass_kg)
        return out


STRUCTURES = ("arm", "plate", "frame", "mast")


def make_structure(name: str) -> _ModalModel:
    """The structure of a rig by its name: "arm" (the default), "plate", "frame" or "mast"."""
    if name == "arm":
        return ModalStructure()
    if name == "plate":
        return PlateStructure()
    if name in ("frame", "mast"):
        from . import beams  # it builds on this module's _ModalModel

        return beams.frame_structure() if name == "frame" else beams.mast_structure()
    raise InputError("structure", f"expected one of {', '.join(STRUCTURES)}; got {name!r}")


def _half_sine_response(s: np.ndarray, duration_s: float, omega: float, zeta: float):
    """Response of x'' + 2 zeta w x' + w^2 x = sin(pi s / T) on [0, T] (0 elsewhere), at rest before.

    With lam = -zeta w + i w_d, I(s) = int_0^min(s,T) exp(lam (s-u)) sin(W u) du and x = Im(I) / w_d.
    Inside the pulse dI/ds = sin(W s) + lam I (the real boundary term drops out of Im), after it
    dI/ds = lam I. Returns (x, x', x'').
    """
    wd = omega * np.sqrt(1.0 - zeta**2)
    lam = complex(-zeta * omega, wd)
    W = np.pi / duration_s
    a = np.clip(s, 0.0, duration_s)
    # int_0^a exp(-lam u) sin(W u) du, in closed form.
    prim = (np.exp(-lam * a) * (-lam * np.sin(W * a) - W * np.cos(W * a)) + W) / (lam**2 + W**2)
    started = s > 0
    during = started & (s < duration_s)
    # exp(lam s) * prim grows no faster than the pulse allows: prim carries exp(-lam a) with a <= s.
    I = np.where(started, np.exp(lam * np.where(started, s, 0.0)) * prim, 0.0)
    dI = lam * I
    ddI = lam * lam * I
    sin_s = np.sin(W * np.where(during, s, 0.0))
    cos_s = np.cos(W * np.where(during, s, 0.0))
    dI = dI + np.where(during, sin_s, 0.0)
    ddI = ddI + np.where(during, W * cos_s + lam * sin_s, 0.0)
    return I.imag / wd, dI.imag / wd, ddI.imag / wd


@dataclass
class Hammer:
    """An impact hammer held by a person: each hit varies in force and place, and may bounce.

    `hit(time_s)` returns the impacts of one hit: the main pulse and, with probability
    `double_hit_probability`, a weaker rebound `double_hit_delay_s` later.
    """

    point_m: tuple[float, float, float]
    direction: tuple[float, float, float]
    peak_n: float = 200.0
    duration_s: float = 1.0e-3
    force_scatter: float = 0.0          # relative standard deviation of the peak force
    point_jitter_m: float = 0.0         # standard deviation of the impact point, per axis
    double_hit_probability: float = 0.0
    double_hit_delay_s: float = 3.0e-3
    double_hit_ratio: float = 0.4       # rebound peak relative to the main peak
    seed: int | None = None

    def __post_init__(self) -> None:
        d = np.asarray(self.direction, float)
        self.direction = tuple(d / np.linalg.norm(d))
        self._rng = np.random.default_rng(self.seed)

    def hit(self, time_s: float, *, double: bool | None = None) -> list[Impact]:
        rng = self._rng
        peak = self.peak_n * max(0.05, 1.0 + self.force_scatter * rng.standard_normal())
        point = tuple(np.asarray(self.point_m, float) + self.point_jitter_m * rng.standard_normal(3))
        impacts = [Impact(time_s, point, self.direction, peak, self.duration_s)]
        if double is None:
            double = rng.random() < self.double_hit_probability
        if double:
            impacts.append(Impact(time_s + self.double_hit_delay_s, point, self.direction,
                                  peak * self.double_hit_ratio, self.duration_s))
        return impacts
