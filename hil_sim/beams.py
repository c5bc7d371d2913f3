"""A small 3D Euler-Bernoulli frame finite-element model, and the rigs built on it ("frame", "mast").

Members are straight, axis-aligned rectangular bars meshed into 12-DOF beam elements (axial, St Venant torsion,
bending about both section axes; consistent mass, with the rotary inertia of torsion). The modes come from
`scipy.linalg.eigh` and are mass-normalised. The 3D displacement of any point of a member's box is the element's
own interpolation (Hermite cubics across, linear along and in twist) carried to the point by rigid plane sections,
so the rendered surface moves exactly as the FE model does.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import eigh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from odsplat.spine.errors import InputError

from .structure import ModeBase, _ModalModel

_TOUCH_M = 1e-3  # how far off a box a point still belongs to it: the structure's tags float 0.5 mm off its faces


@dataclass(frozen=True)
class Material:
    """An isotropic material: Young's modulus, Poisson's ratio, density."""

    name: str
    youngs_modulus_pa: float
    poisson: float
    density_kg_m3: float

    @property
    def shear_modulus_pa(self) -> float:
        return self.youngs_modulus_pa / (2.0 * (1.0 + self.poisson))


STEEL = Material("steel", 210e9, 0.30, 7850.0)
ALUMINIUM = Material("aluminium", 70e9, 0.33, 2700.0)


def torsion_constant(a_m: float, b_m: float, terms: int = 50) -> float:
    """St Venant's torsion constant J of an a x b rectangle (exact series, Timoshenko & Goodier):
    J = a b^3 / 3 [1 - 192 b / (pi^5 a) sum_{n odd} tanh(n pi a / (2 b)) / n^5], a >= b."""
    a, b = max(a_m, b_m), min(a_m, b_m)
    n = 2 * np.arange(terms) + 1.0
    return float(a * b**3 / 3 * (1 - 192 * b / (np.pi**5 * a) * np.sum(np.tanh(n * np.pi * a / (2 * b)) / n**5)))


@dataclass(frozen=True)
class Member:
    """A straight bar along one world axis, from `start_m` to `end_m` (its FE axis, through the section's centre).

    `section_m` is its size along the other two world axes, in axis order (a member along z: (size x, size y)).
    `reach_m` is how far its drawn box goes beyond its ends along its axis (negative: stops short of the end node,
    e.g. a column under a beam); beyond an end the section moves rigidly with the end node."""

    name: str
    start_m: tuple[float, float, float]
    end_m: tuple[float, float, float]
    section_m: tuple[float, float]
    material: Material = STEEL
    n_elements: int = 10
    reach_m: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self) -> None:
        d = np.asarray(self.end_m, float) - np.asarray(self.start_m, float)
        if np.count_nonzero(np.abs(d) > 1e-12) != 1 or d.max() <= 0:
            raise InputError(f"Member {self.name!r}", f"expected a bar along +x, +y or +z; got {self.start_m} to "
                                                      f"{self.end_m}")
        if min(self.section_m) <= 0 or self.n_elements < 1:
            raise InputError(f"Member {self.name!r}", "expected a positive section and at least one element")

    @property
    def axis(self) -> int:
        return int(np.argmax(np.asarray(self.end_m, float) - np.asarray(self.start_m, float)))

    @property
    def length_m(self) -> float:
        return float(np.asarray(self.end_m, float)[self.axis] - np.asarray(self.start_m, float)[self.axis])

    @property
    def frame(self) -> np.ndarray:
        """Rows: the local x (along the member), y and z axes in world coordinates (a cyclic permutation)."""
        a = self.axis
        return np.eye(3)[[a, (a + 1) % 3, (a + 2) % 3]]

    @property
    def local_section_m(self) -> tuple[float, float]:
        """The section's size along local y and local z."""
        others = [(self.axis + 1) % 3, (self.axis + 2) % 3]
        by_axis = dict(zip(sorted(others), self.section_m))
        return by_axis[others[0]], by_axis[others[1]]

    def box(self) -> tuple[np.ndarray, np.ndarray]:
        """The drawn bar as (min corner, max corner)."""
        a, (lo_reach, hi_reach) = self.axis, self.reach_m
        half = np.zeros(3)
        half[sorted([(a + 1) % 3, (a + 2) % 3])] = 0.5 * np.asarray(self.section_m, float)
        lo = np.asarray(self.start_m, float) - half
        hi = np.asarray(self.end_m, float) + half
        lo[a] -= lo_reach
        hi[a] += hi_reach
        return lo, hi


def _element_matrices(m: Member, le: float) -> tuple[np.ndarray, np.ndarray]:
    """Local 12x12 stiffness and consistent mass of one element, DOFs (u, v, w, tx, ty, tz) at each end."""
    by, bz = m.local_section_m
    mat = m.material
    area = by * bz
    iz, iy = bz * by**3 / 12, by * bz**3 / 12      # bending in local y (about z) and in local z (about y)
    e, g, rho = mat.youngs_modulus_pa, mat.shear_modulus_pa, mat.density_kg_m3
    j = torsion_constant(by, bz)
    k = np.zeros((12, 12))
    mm = np.zeros((12, 12))
    bar = np.array([[1.0, -1.0], [-1.0, 1.0]])
    lin = np.array([[2.0, 1.0], [1.0, 2.0]]) / 6
    for dof, stiff, mass in ((0, e * area / le, rho * area * le), (3, g * j / le, rho * (iy + iz) * le)):
        idx = [dof, dof + 6]
        k[np.ix_(idx, idx)] += stiff * bar
        mm[np.ix_(idx, idx)] += mass * lin
    L = le
    kb = np.array([[12, 6 * L, -12, 6 * L], [6 * L, 4 * L * L, -6 * L, 2 * L * L],
                   [-12, -6 * L, 12, -6 * L], [6 * L, 2 * L * L, -6 * L, 4 * L * L]]) / L**3
    mb = np.array([[156, 22 * L, 54, -13 * L], [22 * L, 4 * L * L, 13 * L, -3 * L * L],
                   [54, 13 * L, 156, -22 * L], [-13 * L, -3 * L * L, -22 * L, 4 * L * L]]) * rho * area * L / 420
    # (v, tz) bend with dv/dx = tz; (w, ty) with dw/dx = -ty, hence the sign flips of the rotations.
    for idx, sign, inertia in (([1, 5, 7, 11], 1.0, iz), ([2, 4, 8, 10], -1.0, iy)):
        s = np.diag([1.0, sign, 1.0, sign])
        k[np.ix_(idx, idx)] += e * inertia * s @ kb @ s
        mm[np.ix_(idx, idx)] += s @ mb @ s
    return k, mm


@dataclass(frozen=True)
class FrameModes:
    """The solved model: natural frequencies, and mass-normalised mode vectors over every node's 6 DOFs
    (u_x, u_y, u_z, theta_x, theta_y, theta_z in world axes; zero at clamped nodes), (6 n_nodes, n_modes)."""

    freqs_hz: np.ndarray
    vectors: np.ndarray


class FrameModel:
    """The FE model of a set of members, meshed (nodes where members meet are shared) and clamped at `clamped_m`."""

    def __init__(self, members: Sequence[Member], clamped_m: Sequence[Sequence[float]]):
        self.members = tuple(members)
        nodes: dict[tuple[float, ...], int] = {}
        self.member_nodes: list[np.ndarray] = []
        for m in self.members:
            s = np.linspace(0.0, 1.0, m.n_elements + 1)[:, None]
            pts = np.asarray(m.start_m, float) + s * (np.asarray(m.end_m, float) - np.asarray(m.start_m, float))
            self.member_nodes.append(np.array([nodes.setdefault(tuple(np.round(p, 9)), len(nodes)) for p in pts]))
        self.nodes_m = np.array(list(nodes), float)
        clamped = [nodes.get(tuple(np.round(np.asarray(c, float), 9))) for c in clamped_m]
        if None in clamped:
            raise InputError("FrameModel.clamped_m", f"every clamp must be at a member's node; got {clamped_m}")
        self.clamped = np.array(sorted(set(clamped)), int)
        self._check_connected()
        n = 6 * len(self.nodes_m)
        self.stiffness = np.zeros((n, n))
        self.mass = np.zeros((n, n))
        for m, ids in zip(self.members, self.member_nodes):
            k, mm = _element_matrices(m, m.length_m / m.n_elements)
            rot = np.kron(np.eye(4), m.frame)                  # world DOFs to local, per 3-vector
            k, mm = rot.T @ k @ rot, rot.T @ mm @ rot
            for a, b in zip(ids[:-1], ids[1:]):
                dofs = np.r_[6 * a:6 * a + 6, 6 * b:6 * b + 6]
                self.stiffness[np.ix_(dofs, dofs)] += k
                self.mass[np.ix_(dofs, dofs)] += mm
        fixed = np.zeros(n, bool)
        for c in self.clamped:
            fixed[6 * c:6 * c + 6] = True
        self.free = np.flatnonzero(~fixed)

    def _check_connected(self) -> None:
        """Every member must hang, through shared nodes, from a clamp: a member whose end meets another between its
        nodes is not joined to it (give that one a number of elements that puts a node there)."""
        pairs = np.vstack([np.c_[ids[:-1], ids[1:]] for ids in self.member_nodes])
        n = len(self.nodes_m)
        graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
        _, label = connected_components(graph, directed=False)
        held = np.isin(label, label[self.clamped])
        loose = sorted({m.name for m, ids in zip(self.members, self.member_nodes) if not held[ids].all()})
        if loose:
            raise InputError("FrameModel.members", f"not joined to a clamp through shared nodes: {', '.join(loose)}")

    def solve(self, n_modes: int) -> FrameModes:
        """The n_modes lowest modes (generalised symmetric eigenproblem on the free DOFs, phi^T M phi = I)."""
        f = self.free
        if not 1 <= n_modes <= len(f):
            raise InputError("FrameModel.solve", f"expected 1 to {len(f)} modes (the free DOFs); got {n_modes}")
        w2, vec = eigh(self.stiffness[np.ix_(f, f)], self.mass[np.ix_(f, f)], subset_by_index=[0, n_modes - 1])
        full = np.zeros((6 * len(self.nodes_m), n_modes))
        full[f] = vec
        # A mode's sign is arbitrary: fix it so that its largest translation is positive, the first one within 0.1 %
        # of the largest where several tie (a symmetric frame), so the shapes' signs do not hang on round-off.
        trans = full.reshape(-1, 6, n_modes)[:, :3].reshape(-1, n_modes)
        first = np.argmax(np.abs(trans) >= 0.999 * np.abs(trans).max(axis=0), axis=0)
        full *= np.sign(trans[first, np.arange(n_modes)])
        return FrameModes(np.sqrt(np.maximum(w2, 0.0)) / (2 * np.pi), full)

    def owner(self, points_m: np.ndarray, tol_m: float = _TOUCH_M) -> np.ndarray:
        """The index of the member each point belongs to (-1: none): the first member, in order, whose box holds it
        within tol_m. Where boxes meet (a joint), the member listed first owns the shared face."""
        p = np.atleast_2d(np.asarray(points_m, float))
        out = np.full(len(p), -1)
        for i, m in enumerate(self.members):
            lo, hi = m.box()
            inside = np.all((p >= lo - tol_m) & (p <= hi + tol_m), axis=1) & (out < 0)
            out[inside] = i
        return out

    def displacement(self, points_m: np.ndarray, vectors: np.ndarray, tol_m: float = _TOUCH_M) -> np.ndarray:
        """(P, n_modes, 3): each mode's displacement at the points, as the elements interpolate it, carried by rigid
        plane sections (u = u_c + theta x (p - c)); zero off every member."""
        p = np.atleast_2d(np.asarray(points_m, float))
        out = np.zeros((len(p), vectors.shape[1], 3))
        owner = self.owner(p, tol_m)
        for i, (m, ids) in enumerate(zip(self.members, self.member_nodes)):
            sel = np.flatnonzero(owner == i)
            if sel.size:
                out[sel] = _member_displacement(m, ids, p[sel], vectors)
        return out


def _member_displacement(m: Member, ids: np.ndarray, p: np.ndarray, vectors: np.ndarray) -> np.ndarray:
    """The interpolated displacement of points of one member's box (see FrameModel.displacement)."""
    a, le = m.axis, m.length_m / m.n_elements
    s = np.clip(p[:, a] - m.start_m[a], 0.0, m.length_m)
    e = np.minimum((s / le).astype(int), m.n_elements - 1)
    xi = s / le - e
    nodal = vectors.reshape(-1, 6, vectors.shape[1])                # (nodes, 6, n_modes)
    rot = m.frame
    # Each end's DOFs in local axes: (P, 6, n_modes) at the element's first and second node.
    ends = [np.concatenate([np.einsum("ij,pjk->pik", rot, nodal[ids[e + k], :3]),
                            np.einsum("ij,pjk->pik", rot, nodal[ids[e + k], 3:])], axis=1) for k in (0, 1)]
    d0, d1 = ends
    x = xi[:, None]
    h1, h2, h3, h4 = 1 - 3 * x**2 + 2 * x**3, le * (x - 2 * x**2 + x**3), 3 * x**2 - 2 * x**3, le * (x**3 - x**2)
    g1, g2, g3, g4 = (-6 * x + 6 * x**2) / le, 1 - 4 * x + 3 * x**2, (6 * x - 6 * x**2) / le, 3 * x**2 - 2 * x
    u = (1 - x) * d0[:, 0] + x * d1[:, 0]
    v = h1 * d0[:, 1] + h2 * d0[:, 5] + h3 * d1[:, 1] + h4 * d1[:, 5]
    w = h1 * d0[:, 2] - h2 * d0[:, 4] + h3 * d1[:, 2] - h4 * d1[:, 4]
    tx = (1 - x) * d0[:, 3] + x * d1[:, 3]
    ty = -(g1 * d0[:, 2] - g2 * d0[:, 4] + g3 * d1[:, 2] - g4 * d1[:, 4])
    tz = g1 * d0[:, 1] + g2 * d0[:, 5] + g3 * d1[:, 1] + g4 * d1[:, 5]
    centre = np.stack([u, v, w], axis=1)                            # (P, 3, n_modes), local axes
    theta = np.stack([tx, ty, tz], axis=1)
    c = np.asarray(m.start_m, float) + s[:, None] * rot[0]
    r = (p - c) @ rot.T                                             # the point from its section's centre, local
    disp = centre + np.cross(theta, r[:, :, None], axisa=1, axisb=1, axisc=1)
    return np.einsum("ji,pjk->pki", rot, disp)                      # back to world axes, (P, n_modes, 3)


# ------------------------------------------------------------------------------------ rigs built on the model

_FACES = {"+x": (0, 1), "-x": (0, -1), "+y": (1, 1), "-y": (1, -1), "+z": (2, 1), "-z": (2, -1)}


@dataclass(frozen=True)
class BeamGeometry:
    """A rig of members (moving, FE) and blocks (bolted down: static), with the structure's two tags on faces.

    `tags` are (box name, face) pairs: each tag lies centred on that (vertical) face of that box."""

    members: tuple[Member, ...]
    blocks: tuple[tuple[str, tuple[float, float, float], tuple[float, float, float]], ...]
    clamped_m: tuple[tuple[float, float, float], ...]
    tags: tuple[tuple[str, str], ...] = ()

    def boxes(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """Each member and block as (min corner, max corner)."""
        out = {m.name: m.box() for m in self.members}
        out.update({name: (np.asarray(lo, float), np.asarray(hi, float)) for name, lo, hi in self.blocks})
        return out

    @property
    def floor_clear_radius_m(self) -> float:
        """How far from the z axis the structure reaches over the floor (its boxes standing on it)."""
        corners = [np.hypot(x, y) for lo, hi in self.boxes().values() if lo[2] <= 1e-9
                   for x in (lo[0], hi[0]) for y in (lo[1], hi[1])]
        return float(max(corners))

    def face_point(self, box: str, face: str, along: float = 0.5, height: float = 0.5) -> tuple[float, float, float]:
        """A point on a face of a box: `face` as "+x", "-y", ...; `along` and `height` are fractions across the face
        (along: the first other axis in x, y, z order; height: the second)."""
        lo, hi = self.boxes()[box]
        axis, sign = _FACES[face]
        first, second = (a for a in range(3) if a != axis)
        p = lo.copy()
        p[first] += along * (hi[first] - lo[first])
        p[second] += height * (hi[second] - lo[second])
        p[axis] = hi[axis] if sign > 0 else lo[axis]
        return tuple(float(v) for v in p)

    def tag_mounts(self) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """The structure's tags as (centre, image x axis, image y axis), 0.5 mm off the middle of their (vertical)
        faces, upright: image y down the world's z."""
        out = []
        ez = np.eye(3)[2]
        for box, face in self.tags:
            axis, sign = _FACES[face]
            normal = sign * np.eye(3)[axis]
            centre = np.asarray(self.face_point(box, face), float) + 5e-4 * normal
            out.append((centre, np.cross(ez, normal), -ez))
        return out


@dataclass(frozen=True)
class BeamMode(ModeBase):
    """One mode of a beam rig: natural frequency (FE), damping ratio (set), and what it looks like."""


@dataclass
class BeamStructure(_ModalModel):
    """A rig whose modes are the lowest of its FE model (`FrameModel`), with damping ratios and names set per mode."""

    name: str
    geometry: BeamGeometry
    mode_names: tuple[str, ...]
    damping_ratios: tuple[float, ...]
    modes: tuple[BeamMode, ...] = field(init=False)

    def __post_init__(self) -> None:
        if len(self.mode_names) != len(self.damping_ratios):
            raise InputError(f"BeamStructure {self.name!r}", "expected one damping ratio per mode name")
        self.model = FrameModel(self.geometry.members, self.geometry.clamped_m)
        solved = self.model.solve(len(self.mode_names))
        self.vectors = solved.vectors
        self.modes = tuple(BeamMode(float(f), float(z), n)
                           for f, z, n in zip(solved.freqs_hz, self.damping_ratios, self.mode_names))

    def mode_shapes(self, points_m: np.ndarray) -> np.ndarray:
        """Mass-normalised 3D mode shapes at rest positions: (P, n_modes, 3), in 1/sqrt(kg); zero off the members
        (on the blocks, and in the air)."""
        return self.model.displacement(np.atleast_2d(np.asarray(points_m, float)), self.vectors)


def frame_geometry() -> BeamGeometry:
    """The portal frame, all aluminium: two 25 x 25 mm columns, clamped in foot blocks 0.44 m apart, joined at
    0.60 m by a 50 x 20 mm flat top beam along x, with a 30 x 20 mm stub sticking out 0.125 m along +y from the
    beam's middle (it turns the frame's torsion about the vertical into motion along x). Centred on x = 0.2 m (the
    plan's target); its tags are on the foot blocks' outer faces (the members are too narrow for one)."""
    x0, x1, z_foot, z_beam = -0.02, 0.42, 0.09, 0.60
    col, beam, stub, al = (0.025, 0.025), (0.05, 0.02), (0.03, 0.02), ALUMINIUM
    xc = round(0.5 * (x0 + x1), 9)
    members = (
        Member("stub", (xc, 0.0, z_beam), (xc, 0.15, z_beam), stub, al, 6, (-0.5 * beam[0], 0.0)),
        Member("beam", (x0, 0.0, z_beam), (x1, 0.0, z_beam), beam, al, 10, (0.5 * col[0],) * 2),
        Member("column0", (x0, 0.0, z_foot), (x0, 0.0, z_beam), col, al, 10, (0.0, -0.5 * beam[1])),
        Member("column1", (x1, 0.0, z_foot), (x1, 0.0, z_beam), col, al, 10, (0.0, -0.5 * beam[1])),
    )
    blocks = tuple((f"foot{k}", (x - 0.05, -0.05, 0.0), (x + 0.05, 0.05, z_foot)) for k, x in enumerate((x0, x1)))
    return BeamGeometry(members, blocks, ((x0, 0.0, z_foot), (x1, 0.0, z_foot)),
                        tags=(("foot0", "-y"), ("foot1", "+y")))


def mast_geometry() -> BeamGeometry:
    """The mast: a 19.4 (x) x 20.0 (y) mm steel bar standing 0.63 m out of a 120 mm square base block 90 mm high
    at (0.2, 0) m. Its section is almost square, so its bending modes come in closely spaced x-y pairs; its tags are
    on the base block (the mast is too narrow for one)."""
    xc, z_base, top = 0.2, 0.09, 0.72
    mast = Member("mast", (xc, 0.0, z_base), (xc, 0.0, top), (0.0194, 0.0200), n_elements=12)
    block = ("base", (xc - 0.06, -0.06, 0.0), (xc + 0.06, 0.06, z_base))
    return BeamGeometry((mast,), (block,), ((xc, 0.0, z_base),), tags=(("base", "-y"), ("base", "+y")))


FRAME_MODES = ("sway out of plane (y), beam twisting", "sway along the beam (x)",
               "torsion about the vertical (columns in y, opposite)", "beam vertical bending (stub nodding)",
               "columns' second bending out of plane with the stub nodding")
FRAME_DAMPINGS = (0.010, 0.008, 0.015, 0.012, 0.020)
MAST_MODES = ("first bending x", "first bending y", "second bending x", "second bending y")
MAST_DAMPINGS = (0.008, 0.007, 0.012, 0.014)


def frame_structure() -> BeamStructure:
    """The "frame" rig (see frame_geometry), its five lowest FE modes."""
    return BeamStructure("frame", frame_geometry(), FRAME_MODES, FRAME_DAMPINGS)


def mast_structure() -> BeamStructure:
    """The "mast" rig (see mast_geometry), its four lowest FE modes: two closely spaced bending pairs."""
    return BeamStructure("mast", mast_geometry(), MAST_MODES, MAST_DAMPINGS)
