"""The simulated rig's scene: the textured structure, a floor with AprilTag boards, tags on the structure.

Everything is one textured triangle mesh with a texture atlas. Structure vertices carry their mode
shapes, so the deformed mesh at any modal state is `rest + shapes @ q`, scaled by alpha for the
natively magnified ground-truth renders. `SceneSettings` varies what a rig of another lab would:
the tags' size and the structure's texture (a speckle, value noise, or a repetitive checker).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.ndimage import gaussian_filter

from odsplat.spine.errors import InputError
from odsplat.spine.manifest import TagLayout, TagPlacement

from .render import TexturedMesh, lambert_shade
from .structure import ModalStructure, PlateStructure

STRUCTURE, FLOOR, FLOOR_TAG, STRUCTURE_TAG = 1, 2, 3, 4
# Colours for RGB scenes: a painted (orange) structure on a grey floor, black-and-white tags.
_TINT = {STRUCTURE: (0.95, 0.55, 0.20), FLOOR: (0.80, 0.80, 0.78),
         FLOOR_TAG: (1.0, 1.0, 1.0), STRUCTURE_TAG: (1.0, 1.0, 1.0)}
_TAG_CELLS = 10  # a tag36h11 image is 8 cells of black-bordered code plus a 1-cell white quiet zone each side


@dataclass
class _Builder:
    """Accumulates textured quads (as grids of triangles) and the atlas rectangles they sample."""

    vertices: list[np.ndarray] = field(default_factory=list)
    uv: list[np.ndarray] = field(default_factory=list)
    faces: list[np.ndarray] = field(default_factory=list)
    object_id: list[np.ndarray] = field(default_factory=list)
    textures: list[np.ndarray] = field(default_factory=list)
    n_vertices: int = 0
    rgb: bool = False

    def quad(self, origin, u_axis, v_axis, size_u_m, size_v_m, cell_m, texture, obj) -> None:
        """A planar rectangle origin + a*u + b*v, a in [0, size_u], b in [0, size_v]; texture row = v."""
        nu = max(1, int(np.ceil(size_u_m / cell_m)))
        nv = max(1, int(np.ceil(size_v_m / cell_m)))
        a = np.linspace(0.0, 1.0, nu + 1)
        b = np.linspace(0.0, 1.0, nv + 1)
        A, B = np.meshgrid(a, b)  # (nv+1, nu+1)
        pts = (np.asarray(origin, float) + A[..., None] * size_u_m * np.asarray(u_axis, float)
               + B[..., None] * size_v_m * np.asarray(v_axis, float))
        th, tw = texture.shape[:2]
        # Texel centres sit at integer coordinates, so the rectangle spans [-0.5, size - 0.5].
        uv = np.stack([A * tw - 0.5, B * th - 0.5], axis=-1)
        idx = np.arange((nu + 1) * (nv + 1)).reshape(nv + 1, nu + 1) + self.n_vertices
        v00, v01, v10, v11 = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
        tris = np.concatenate([np.stack([v00, v10, v11], -1).reshape(-1, 3),
                               np.stack([v00, v11, v01], -1).reshape(-1, 3)])
        self.vertices.append(pts.reshape(-1, 3))
        self.uv.append(uv.reshape(-1, 2).astype(np.float32))
        self.faces.append(tris.astype(np.int32))
        self.object_id.append(np.full(len(tris), obj, np.int16))
        if self.rgb:
            texture = texture[..., None] * np.asarray(_TINT[obj], np.float32)
        self.textures.append(texture.astype(np.float32))
        self.n_vertices += len(pts.reshape(-1, 3))

    def pack(self) -> tuple[np.ndarray, np.ndarray]:
        """Shelf-pack the textures into one atlas; returns (atlas, uv shifted into it)."""
        width = max(2048, max(t.shape[1] for t in self.textures) + 2)
        x = y = shelf = 0
        offsets = []
        for tex in self.textures:
            h, w = tex.shape[:2]
            if x + w + 2 > width:
                x, y, shelf = 0, y + shelf + 2, 0
            offsets.append((x + 1, y + 1))
            x += w + 2
            shelf = max(shelf, h)
        atlas = np.zeros((y + shelf + 2, width) + self.textures[0].shape[2:], np.float32)
        uv = []
        for tex, (ox, oy), uvs in zip(self.textures, offsets, self.uv):
            h, w = tex.shape[:2]
            # A one-texel border copied from the edge keeps bilinear lookups at the rim honest.
            pad = ((1, 1), (1, 1)) + ((0, 0),) * (tex.ndim - 2)
            atlas[oy - 1:oy + h + 1, ox - 1:ox + w + 1] = np.pad(tex, pad, mode="edge")
            uv.append(uvs + np.array([ox, oy], np.float32))
        return atlas, np.concatenate(uv)


def speckle(shape: tuple[int, int], grain_texels: float, rng: np.random.Generator, *,
            low: float = 0.12, high: float = 0.88) -> np.ndarray:
    """A smooth random speckle with grains of about `grain_texels`, spanning [low, high]."""
    field_ = gaussian_filter(rng.standard_normal(shape), grain_texels / 2.0, mode="wrap")
    field_ = (field_ - field_.mean()) / (field_.std() + 1e-12)
    return (low + (high - low) / (1.0 + np.exp(-1.8 * field_))).astype(np.float32)


def tag_texture(tag_id: int, texels_per_cell: int) -> np.ndarray:
    """A tag36h11 image (black code, 8 cells) with a white quiet zone of one cell, values 0.05 / 0.95."""
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
    code = cv2.aruco.generateImageMarker(dictionary, tag_id, 8 * texels_per_cell)
    img = np.pad(code, texels_per_cell, constant_values=255).astype(np.float32) / 255.0
    return 0.05 + 0.9 * img


def value_noise(shape: tuple[int, int], grain_texels: float, rng: np.random.Generator, *, octaves: int = 4,
                low: float = 0.12, high: float = 0.88) -> np.ndarray:
    """Procedural value noise: random values on lattices of 8, 4, 2 and 1 x `grain_texels` (halving amplitude),
    smoothstep-interpolated, stretched to span [low, high] (1st to 99th percentile). Smoother and less
    contrasty than the speckle: most of its energy sits at the coarse scales."""
    h, w = shape
    acc = np.zeros(shape)
    total = 0.0
    for o in range(octaves):
        cell = max(grain_texels * 2 ** (octaves - 1 - o), 1.0)
        amp = 2.0 ** -o
        lattice = rng.random((int(np.ceil(h / cell)) + 2, int(np.ceil(w / cell)) + 2))
        y, x = np.arange(h) / cell, np.arange(w) / cell
        iy, ix = np.floor(y).astype(int), np.floor(x).astype(int)
        fy, fx = y - iy, x - ix
        sy, sx = (fy * fy * (3 - 2 * fy))[:, None], fx * fx * (3 - 2 * fx)
        top = lattice[iy][:, ix] * (1 - sx) + lattice[iy][:, ix + 1] * sx
        bottom = lattice[iy + 1][:, ix] * (1 - sx) + lattice[iy + 1][:, ix + 1] * sx
        acc += amp * (top * (1 - sy) + bottom * sy)
        total += amp
    lo, hi = np.percentile(acc, [1, 99])
    return np.clip(low + (high - low) * (acc - lo) / max(hi - lo, 1e-12), low, high).astype(np.float32)


def checker(shape: tuple[int, int], cell_texels: float, *, low: float = 0.12, high: float = 0.88) -> np.ndarray:
    """A repetitive pattern: a checkerboard of `cell_texels` squares. Every patch looks like its neighbours
    one period away, as a regular paint pattern or a perforated sheet does."""
    cell = max(int(round(cell_texels)), 1)
    j, i = np.indices(shape)
    return np.where((i // cell + j // cell) % 2 == 0, low, high).astype(np.float32)


TEXTURES = ("speckle", "value_noise", "checker")


@dataclass(frozen=True)
class SceneSettings:
    """What varies between rigs' scenes. The defaults are hil_sim's own scene, exactly."""

    floor_tag_size_m: float = 0.12        # the floor tags' black square; ~32 px at 400x300 from 1.6 m, ~20 px at 256
    structure_tag_size_m: float = 0.06
    texture: str = "speckle"              # the structure's: "speckle", "value_noise" or "checker"
    texture_grain_m: float = 0.004        # speckle grain, finest value-noise lattice, checker square

    def __post_init__(self) -> None:
        for name in ("floor_tag_size_m", "structure_tag_size_m"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and 0.016 <= v <= 0.3):
                raise InputError(f"SceneSettings.{name}", f"expected 0.016 to 0.3 m (2 mm tag cells and up); got {v!r}")
        if self.texture not in TEXTURES:
            raise InputError("SceneSettings.texture", f"expected one of {', '.join(TEXTURES)}; got {self.texture!r}")
        g = self.texture_grain_m
        if not (isinstance(g, (int, float)) and math.isfinite(g) and 0.002 <= g <= 0.05):
            raise InputError("SceneSettings.texture_grain_m", f"expected 2 to 50 mm; got {g!r}")


@dataclass
class RigScene:
    """The rig's mesh at rest, the mode shapes of its vertices, the atlas and the tag layout."""

    structure: ModalStructure | PlateStructure
    rest_m: np.ndarray          # (V, 3)
    faces: np.ndarray           # (F, 3)
    uv_px: np.ndarray           # (V, 2)
    object_id: np.ndarray       # (F,)
    shapes: np.ndarray          # (V, n_modes, 3) mass-normalised mode shapes, zero off the structure
    atlas: np.ndarray
    tags: TagLayout
    light_dir: np.ndarray = field(default_factory=lambda: np.array([-0.4, -0.6, -1.0]))
    settings: SceneSettings = field(default_factory=SceneSettings)

    def deformed(self, q: np.ndarray | None = None, alpha: float = 1.0) -> np.ndarray:
        """Vertex positions for modal coordinates q (n_modes,), with the motion multiplied by alpha."""
        if q is None:
            return self.rest_m
        return self.rest_m + alpha * np.einsum("vkc,k->vc", self.shapes, np.asarray(q, float))

    def mesh(self, q: np.ndarray | None = None, alpha: float = 1.0) -> TexturedMesh:
        verts = self.deformed(q, alpha)
        return TexturedMesh(vertices_m=verts, faces=self.faces, uv_px=self.uv_px, object_id=self.object_id,
                            shade=lambert_shade(verts, self.faces, self.light_dir))

    def structure_vertices(self) -> np.ndarray:
        """Indices of the vertices that move with the structure."""
        moving = np.isin(self.object_id, (STRUCTURE, STRUCTURE_TAG))
        return np.unique(self.faces[moving])


def build_scene(structure: ModalStructure | PlateStructure | None = None, settings: SceneSettings | None = None, *,
                cell_m: float = 0.01, texel_m: float = 1e-3, floor_half_m: float = 0.75, rgb: bool = False,
                seed: int = 0) -> RigScene:
    """The rig's scene: the structure with a material-fixed texture, a floor with 8 tag boards around it (made
    larger when they would not fit), 2 tags on the structure. Defaults: the arm, as hil_sim always had it."""
    structure = structure or ModalStructure()
    settings = settings or SceneSettings()
    floor_tag_size_m, structure_tag_size_m = settings.floor_tag_size_m, settings.structure_tag_size_m
    grain = settings.texture_grain_m / texel_m
    rng = np.random.default_rng(seed)
    b = _Builder(rgb=rgb)
    ex, ey, ez = np.eye(3)
    for name, (lo, hi) in structure.geometry.boxes().items():
        size = hi - lo
        # Each visible side as (origin, u, v, size_u, size_v) with u x v = -outward normal: the
        # triangles then wind counter-clockwise seen from outside, and texture images are unmirrored.
        # Hidden sides (on the floor, inside another box) are left out.
        sides = [
            (np.array([lo[0], hi[1], hi[2]]), ex, -ey, size[0], size[1]),       # top, normal +z
            (np.array([lo[0], lo[1], hi[2]]), ex, -ez, size[0], size[2]),       # normal -y
            (np.array([hi[0], hi[1], hi[2]]), -ex, -ez, size[0], size[2]),      # normal +y
            (np.array([lo[0], hi[1], hi[2]]), -ey, -ez, size[1], size[2]),      # normal -x
            (np.array([hi[0], lo[1], hi[2]]), ey, -ez, size[1], size[2]),       # normal +x
        ]
        if name == "arm":
            sides = [s for i, s in enumerate(sides) if i != 3]                  # its root is in the column
            sides.append((np.array([lo[0], lo[1], lo[2]]), ex, ey, size[0], size[1]))  # underside, normal -z
        for origin, u, v, su, sv in sides:
            shape = (max(2, round(sv / texel_m)), max(2, round(su / texel_m)))
            if settings.texture == "speckle":
                tex = speckle(shape, grain, rng)
            elif settings.texture == "value_noise":
                tex = value_noise(shape, grain, rng)
            else:
                tex = checker(shape, grain)
            b.quad(origin, u, v, su, sv, cell_m, tex, STRUCTURE)

    ring = structure.geometry.floor_clear_radius_m + 0.22
    floor_half_m = max(floor_half_m, ring + floor_tag_size_m * _TAG_CELLS / 8 + 0.05)
    floor_texel = 2 * texel_m
    n = round(2 * floor_half_m / floor_texel)
    b.quad((-floor_half_m, floor_half_m, 0.0), ex, -ey, 2 * floor_half_m, 2 * floor_half_m, 2 * floor_half_m / 4,
           speckle((n, n), 6.0, rng, low=0.35, high=0.7), FLOOR)

    placements = []
    cells = max(1, round(floor_tag_size_m / 8 / texel_m))
    for k in range(8):
        ang = np.pi / 4 * k
        centre = np.array([ring * np.cos(ang), ring * np.sin(ang), 5e-4])
        # Image x along u and image y along v, with u x v = -normal: unmirrored seen from above.
        u = np.array([-np.sin(ang), np.cos(ang), 0.0])
        v = np.cross(u, ez)  # radially outward: the tag's top edge faces the structure
        placements.append(_add_tag(b, k, centre, u, v, floor_tag_size_m, cells, FLOOR_TAG))
    cells = max(1, round(structure_tag_size_m / 8 / texel_m))
    for k, (centre, u, v) in enumerate(structure.geometry.tag_mounts()):
        placements.append(_add_tag(b, 100 + k, centre, u, v, structure_tag_size_m, cells, STRUCTURE_TAG))

    atlas, uv = b.pack()
    rest = np.concatenate(b.vertices)
    faces = np.concatenate(b.faces)
    object_id = np.concatenate(b.object_id)
    shapes = np.zeros((len(rest), structure.n_modes, 3))
    moving = np.unique(faces[np.isin(object_id, (STRUCTURE, STRUCTURE_TAG))])
    shapes[moving] = structure.mode_shapes(rest[moving])
    layout = TagLayout(family="tag36h11", size_m=floor_tag_size_m, tags=placements)
    return RigScene(structure, rest, faces, uv, object_id, shapes, atlas, layout, settings=settings)


def _add_tag(b: _Builder, tag_id: int, centre: np.ndarray, u: np.ndarray, v: np.ndarray, size_m: float,
             texels_per_cell: int, obj: int) -> TagPlacement:
    """A tag quad with its quiet zone; returns its black-square corners in the normalised order."""
    full = size_m * _TAG_CELLS / 8
    origin = centre - 0.5 * full * (u + v)
    b.quad(origin, u, v, full, full, full, tag_texture(tag_id, texels_per_cell), obj)
    h = 0.5 * size_m
    # OpenCV's marker corner order: top-left, top-right, bottom-right, bottom-left in the tag image.
    corners = [centre + h * (-u - v), centre + h * (u - v), centre + h * (u + v), centre + h * (-u + v)]
    return TagPlacement(id=tag_id, corners_m=[c.round(9).tolist() for c in corners], on_structure=obj == STRUCTURE_TAG,
                        size_m=size_m)
