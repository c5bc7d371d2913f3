"""Gaussians: initialisation from points, the INRIA .ply layout, and the neighbour priors' invariances."""
import math

import numpy as np
import pytest
import torch

from odsplat.processing.metrics import ssim as metric_ssim
from odsplat.reconstruction.gaussians import SH_C0, Gaussians, load_ply, save_ply
from odsplat.reconstruction.losses import Neighbours, image_loss, ssim
from odsplat.reconstruction.quaternion import quat_multiply, quat_to_matrix
from odsplat.spine.errors import InputError, SchemaError


def _cloud(n=200, seed=0):
    rng = np.random.default_rng(seed)
    return rng.uniform(-1, 1, (n, 3)), rng.uniform(0.1, 0.9, (n, 1))


def test_from_points_scales_follow_spacing():
    # A grid with 0.01 spacing: each point's three nearest neighbours are 0.01 away.
    g = np.stack(np.meshgrid(*[np.arange(6) * 0.01] * 3, indexing="ij"), -1).reshape(-1, 3)
    gs = Gaussians.from_points(g, np.full((len(g), 1), 0.5), opacity=0.1)
    assert np.allclose(gs.scales.numpy(), 0.01, rtol=1e-5)
    assert np.allclose(gs.opacities.numpy(), 0.1, rtol=1e-4)
    assert np.allclose(gs.colors.numpy(), 0.5, atol=1e-6)


def test_ply_round_trip_and_inria_fields(tmp_path):
    pts, col = _cloud()
    g = Gaussians.from_points(pts, np.repeat(col, 3, axis=1))
    g.quats = torch.nn.functional.normalize(torch.randn(len(g), 4, generator=torch.Generator().manual_seed(1)), dim=-1)
    path = save_ply(g, tmp_path / "g.ply")
    header = path.read_bytes().split(b"end_header\n")[0].decode()
    for name in ("x", "f_dc_0", "f_rest_44", "opacity", "scale_2", "rot_3"):
        assert f"property float {name}\n" in header + "\n"
    back = load_ply(path)
    assert torch.allclose(back.means, g.means, atol=1e-6)
    assert torch.allclose(back.log_scales, g.log_scales, atol=1e-6)
    assert torch.allclose(back.opacities, g.opacities, atol=1e-6)
    assert torch.allclose(back.colors, g.colors, atol=1e-5)
    assert torch.allclose(back.unit_quats, g.unit_quats, atol=1e-6)
    # The DC term is what viewers show: colour 0.5 + SH_C0 * f_dc.
    raw = np.frombuffer(path.read_bytes().split(b"end_header\n")[1], "<f4").reshape(len(g), -1)
    assert np.allclose(0.5 + SH_C0 * raw[:, 6], g.colors[:, 0].numpy(), atol=1e-5)


def test_ply_header_is_inria_and_other_encodings_read_back(tmp_path):
    """The header is exactly the INRIA layout (62 float properties); an ASCII copy written by plyfile, as other
    tools may write, reads back to the same Gaussians; a truncated body is refused naming the file."""
    from plyfile import PlyData

    pts, col = _cloud()
    g = Gaussians.from_points(pts, np.repeat(col, 3, axis=1))
    path = save_ply(g, tmp_path / "g.ply")
    names = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(45)]
             + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])
    header = path.read_bytes().split(b"end_header\n")[0].decode().splitlines()
    assert header == ["ply", "format binary_little_endian 1.0", f"element vertex {len(g)}",
                      *(f"property float {n}" for n in names)]
    assert path.stat().st_size == len("\n".join(header)) + len("\nend_header\n") + len(g) * len(names) * 4
    ply = PlyData.read(str(path))
    assert ply["vertex"].count == len(g) and np.allclose(ply["vertex"]["x"], g.means[:, 0].numpy(), atol=1e-6)
    ascii_copy = tmp_path / "ascii.ply"
    PlyData(ply.elements, text=True).write(str(ascii_copy))
    assert ascii_copy.read_bytes().startswith(b"ply\nformat ascii 1.0\n")
    back = load_ply(ascii_copy)
    assert torch.allclose(back.means, g.means, atol=1e-6) and torch.allclose(back.colors, g.colors, atol=1e-5)
    assert torch.allclose(back.unit_quats, g.unit_quats, atol=1e-6)
    cut = tmp_path / "cut.ply"
    cut.write_bytes(path.read_bytes()[:-100])
    with pytest.raises(SchemaError, match="cut.ply"):
        load_ply(cut)


def test_mono_ply_and_transform(tmp_path):
    pts, col = _cloud()
    g = Gaussians.from_points(pts, col)
    mm = g.transformed(1000.0, np.array([1.0, 2.0, 3.0]))
    assert torch.allclose(mm.means, g.means * 1000 + torch.tensor([1.0, 2.0, 3.0], dtype=g.means.dtype))
    assert torch.allclose(mm.scales, g.scales * 1000, rtol=1e-5)
    back = load_ply(save_ply(g, tmp_path / "m.ply"), n_colors=1)
    assert back.n_colors == 1 and torch.allclose(back.colors, g.colors, atol=1e-5)


def test_ply_errors(tmp_path):
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"not a ply")
    with pytest.raises(SchemaError, match="bad.ply"):
        load_ply(bad)
    with pytest.raises(InputError, match="nope.ply"):
        load_ply(tmp_path / "nope.ply")
    mesh = tmp_path / "mesh.ply"
    mesh.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\nend_header\n"
                     + bytes(4))
    with pytest.raises(SchemaError, match="missing"):
        load_ply(mesh)
    with pytest.raises(InputError, match="points"):
        Gaussians.from_points(np.zeros((2, 3)), np.zeros((2, 1)))


def _rotation_quat(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    return torch.tensor([math.cos(angle / 2), *(math.sin(angle / 2) * axis)], dtype=torch.float64)


def test_priors_vanish_under_rigid_motion_and_grow_with_shear():
    pts, _ = _cloud(300, seed=2)
    m0 = torch.as_tensor(pts)
    q0 = torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64).repeat(len(pts), 1)
    nb = Neighbours.build(m0, k=10)
    # A rigid motion: rotate every Gaussian's frame and the cloud by the same rotation, then translate.
    q = _rotation_quat([1, 2, 3], 0.3)
    R = quat_to_matrix(q)
    m1 = m0 @ R.T + torch.tensor([0.1, -0.2, 0.05], dtype=torch.float64)
    q1 = quat_multiply(q.expand(len(pts), 4), q0)
    assert float(nb.rigidity(m0, q0, m1, q1)) < 1e-12
    assert float(nb.rotation(q0, q1)) < 1e-12
    assert float(nb.isometry(m1)) < 1e-12
    # A shear is neither rigid nor isometric; a rotation of the cloud without turning the Gaussians breaks rigidity.
    shear = m0.clone()
    shear[:, 0] += 0.2 * m0[:, 1]
    assert float(nb.isometry(shear)) > 1e-3
    assert float(nb.rigidity(m0, q0, shear, q0)) > 1e-3
    assert float(nb.rigidity(m0, q0, m1, q0)) > 1e-3
    # The weights are unit-free: the same cloud in millimetres gives the same weights.
    assert torch.allclose(Neighbours.build(m0 * 1000, k=10).weight, nb.weight)
    # A random quarter of the neighbourhoods: rigid motion still costs nothing, and over many draws the
    # estimate averages to the full prior (the gradient's scale is kept).
    gen = torch.Generator().manual_seed(0)
    sub = nb.sample(0.25, gen)
    assert sub.index.shape[0] == 75 and nb.sample(1.0) is nb
    assert float(sub.rigidity(m0, q0, m1, q1)) < 1e-12
    draws = [float(nb.sample(0.25, gen).isometry(shear)) for _ in range(400)]
    assert np.mean(draws) == pytest.approx(float(nb.isometry(shear)), rel=0.03)
    assert np.std(draws) > 0


def _moved_cloud(n, seed, dtype=torch.float64):
    pts, _ = _cloud(n, seed=seed)
    gen = torch.Generator().manual_seed(seed)
    m0 = torch.as_tensor(pts, dtype=dtype)
    q0 = torch.nn.functional.normalize(torch.randn(n, 4, generator=gen, dtype=dtype), dim=1)
    m = (m0 + 0.05 * torch.randn(n, 3, generator=gen, dtype=dtype)).requires_grad_(True)
    q = (q0 + 0.1 * torch.randn(n, 4, generator=gen, dtype=dtype)).requires_grad_(True)
    return m0, q0, m, q


@pytest.mark.parametrize("fraction", [1.0, 0.3])
def test_numba_priors_equal_the_torch_definitions(fraction):
    m0, q0, m, q = _moved_cloud(400, seed=3)
    sub = Neighbours.build(m0, k=12).sample(fraction, torch.Generator().manual_seed(1))
    got = {}
    for backend in ("torch", "numba"):
        terms = sub.priors(m0, q0, m, q, backend=backend)
        loss = 4 * terms[0] + 3 * terms[1] + 2 * terms[2]
        got[backend] = (torch.stack(terms).detach(), *torch.autograd.grad(loss, (m, q)))
    for a, b in zip(got["torch"], got["numba"]):
        assert torch.allclose(a, b, rtol=1e-10, atol=1e-14)
    assert float(got["numba"][0].min()) > 1e-3  # every term is exercised
    # The same gradients on one thread as on two (a fixed order of summation).
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = torch.autograd.grad(sum(sub.priors(m0, q0, m, q, backend="numba")), (m, q))
        torch.set_num_threads(2)
        two = torch.autograd.grad(sum(sub.priors(m0, q0, m, q, backend="numba")), (m, q))
    finally:
        torch.set_num_threads(threads)
    assert all(torch.equal(a, b) for a, b in zip(one, two))


def test_numba_priors_gradcheck_and_float32():
    m0, q0, m, q = _moved_cloud(40, seed=4)
    sub = Neighbours.build(m0, k=5)
    assert torch.autograd.gradcheck(lambda mm, qq: torch.stack(sub.priors(m0, q0, mm, qq, backend="numba")), (m, q))
    # float32 (training's dtype) follows float64 to float32 rounding; a rigid motion still costs nothing.
    m32, q32, m0_32, q0_32 = (t.detach().float() for t in (m, q, m0, q0))
    t32 = torch.stack(Neighbours.build(m0_32, k=5).priors(m0_32, q0_32, m32, q32, backend="numba"))
    assert torch.allclose(t32.double(), torch.stack(sub.priors(m0, q0, m, q)).detach(), rtol=1e-5)
    assert sub.priors(m0, q0, m0, q0, backend="numba")[0].item() == pytest.approx(0.0, abs=1e-12)
    with pytest.raises(ValueError, match="backend"):
        sub.priors(m0, q0, m, q, backend="cuda")


def test_ssim_and_image_loss():
    rng = np.random.default_rng(0)
    a = torch.as_tensor(rng.uniform(0, 1, (40, 50, 1)))
    assert float(ssim(a, a)) == pytest.approx(1.0, abs=1e-9)
    b = (a + 0.1 * torch.as_tensor(rng.standard_normal(a.shape))).clamp(0, 1)
    # Away from the zero-padded border the loss's SSIM is the metric's (valid region, no padding).
    from odsplat.spine.similarity import ssim_map
    inner = ssim_map(a.permute(2, 0, 1)[None], b.permute(2, 0, 1)[None], pad=True)[..., 5:-5, 5:-5].mean()
    assert float(inner) == pytest.approx(metric_ssim(a[..., 0], b[..., 0]), abs=1e-12)
    assert 0.85 < float(ssim(a, b)) < 0.97
    assert float(image_loss(a, a)) == pytest.approx(0.0, abs=1e-9)
    l1 = float((a - b).abs().mean())
    assert float(image_loss(a, b, ssim_weight=0.0)) == pytest.approx(l1)
    assert float(image_loss(a, b)) == pytest.approx(0.8 * l1 + 0.2 * (1 - float(ssim(a, b))))
