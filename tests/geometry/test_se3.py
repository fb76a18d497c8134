import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from inrslam.geometry import se3
from inrslam.geometry.angles import rotation_angle_deg_np
from inrslam.geometry.conventions import opencv_to_opengl, opengl_to_opencv


def random_rotations(n, seed=0):
    return torch.from_numpy(Rotation.random(n, random_state=seed).as_matrix())


def test_quat_roundtrip_and_norm_invariance():
    R = random_rotations(50)
    q = se3.matrix_to_quat(R)
    assert torch.allclose(q.norm(dim=-1), torch.ones(50, dtype=q.dtype))
    assert torch.allclose(se3.quat_to_matrix(q), R, atol=1e-12)
    # unnormalised quaternions give the same rotation (factor 2/|q|^2)
    assert torch.allclose(se3.quat_to_matrix(3.7 * q), R, atol=1e-12)
    # agrees with scipy (scalar-last there)
    qs = Rotation.from_matrix(R.numpy()).as_quat()
    ours = q.numpy()[:, [1, 2, 3, 0]]
    assert np.allclose(np.abs((qs * ours).sum(-1)), 1.0, atol=1e-12)


def test_se3_exp_group_properties():
    torch.manual_seed(0)
    xi = torch.randn(20, 6, dtype=torch.float64) * 0.5
    T = se3.se3_exp(xi)
    R = T[:, :3, :3]
    assert torch.allclose(R @ R.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(20, 3, 3), atol=1e-12)
    assert torch.allclose(torch.linalg.det(R), torch.ones(20, dtype=torch.float64))
    # exp(xi) exp(-xi) = I  (one-parameter subgroup)
    assert torch.allclose(T @ se3.se3_exp(-xi), torch.eye(4, dtype=torch.float64).expand(20, 4, 4), atol=1e-12)
    # rotation part equals scipy's rotation vector exp
    Rs = Rotation.from_rotvec(xi[:, 3:].numpy()).as_matrix()
    assert np.allclose(R.numpy(), Rs, atol=1e-12)


def test_se3_exp_smooth_at_zero_and_gradcheck():
    xi0 = torch.zeros(1, 6, dtype=torch.float64, requires_grad=True)
    T = se3.se3_exp(xi0)
    assert torch.allclose(T, torch.eye(4, dtype=torch.float64)[None])
    assert torch.autograd.gradcheck(se3.se3_exp, (xi0,))
    xi = (torch.randn(3, 6, dtype=torch.float64) * 0.3).requires_grad_()
    assert torch.autograd.gradcheck(se3.se3_exp, (xi,))
    # derivative at zero is the generator: d/d(omega_z) of R[0,1] = -1
    T = se3.se3_exp(xi0)
    (g,) = torch.autograd.grad(T[0, 0, 1], xi0)
    assert g[0, 5].item() == pytest.approx(-1.0)


def _hat(xi):
    """(6,) twist -> (4, 4) Lie-algebra matrix [[ [omega]x, rho ], [0, 0]]."""
    M = torch.zeros(4, 4, dtype=xi.dtype)
    M[:3, :3] = se3.skew(xi[3:])
    M[:3, 3] = xi[:3]
    return M


@pytest.mark.parametrize("theta", [0.0, 1e-6, 9e-5, 1.01e-4, 1.5e-4, 3e-4, 1e-3, 1e-2, 0.1, 0.49, 0.51, 1.0, 3.0])
def test_se3_exp_in_float32_is_accurate_to_float32_at_every_angle(theta):
    # the closed forms (1 - cos)/θ² and (θ - sin)/θ³ lose every digit in float32 just above the float64 series'
    # switch (θ = 1e-4): values were off by 1e-4 m and the twist's Jacobian by O(1) there
    g = torch.Generator().manual_seed(int(theta * 1e6))
    for _ in range(4):
        axis = torch.randn(3, dtype=torch.float64, generator=g)
        xi = torch.cat([torch.randn(3, dtype=torch.float64, generator=g), axis / axis.norm() * theta])
        exact = torch.linalg.matrix_exp(_hat(xi))
        assert (se3.se3_exp(xi.float()).double() - exact).abs().max() < 2e-6
        J32 = torch.autograd.functional.jacobian(se3.se3_exp, xi.float()).double()
        J64 = torch.autograd.functional.jacobian(se3.se3_exp, xi)
        assert (J32 - J64).abs().max() < 2e-6
        assert (se3.so3_exp(xi[3:].float()).double() - exact[:3, :3]).abs().max() < 1e-6


def test_se3_exp_float64_matches_the_matrix_exponential():
    torch.manual_seed(1)
    for theta in (0.0, 1e-9, 1e-5, 1e-4, 1e-2, 1.0, 3.0):
        axis = torch.randn(3, dtype=torch.float64)
        xi = torch.cat([torch.randn(3, dtype=torch.float64), axis / axis.norm() * theta])
        # 1e-12: at θ = 1e-4, just above the series, 1 - cos θ keeps 8 of its 16 digits (float64 is left as it was:
        # the photometric alignment's poses depend on its bits)
        assert torch.allclose(se3.se3_exp(xi), torch.linalg.matrix_exp(_hat(xi)), atol=1e-12, rtol=0)


def test_quat_to_matrix_gradcheck():
    q = torch.randn(4, 4, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(se3.quat_to_matrix, (q,))


def test_rotation_angle():
    R = torch.from_numpy(Rotation.from_rotvec([0, 0, math.radians(30)]).as_matrix())
    assert se3.rotation_angle_deg(R).item() == pytest.approx(30.0)
    small = torch.from_numpy(Rotation.from_rotvec([1e-6, 0, 0]).as_matrix())  # acos of the trace reads 0 here
    assert se3.rotation_angle_deg(small).item() == pytest.approx(math.degrees(1e-6), rel=1e-6)
    assert se3.rotation_angle_deg(1.0001 * small).item() == pytest.approx(math.degrees(1e-6), rel=1e-3)  # scaled
    flip = torch.from_numpy(Rotation.from_rotvec([0, math.pi, 0]).as_matrix())
    assert se3.rotation_angle_deg(flip).item() == pytest.approx(180.0)


def test_rotation_angle_deg_np_matches_the_torch_form_and_is_exact_near_zero():
    rots = Rotation.random(16, random_state=np.random.default_rng().integers(1 << 31)).as_matrix()
    ang = rotation_angle_deg_np(rots)
    assert ang.shape == (16,)
    np.testing.assert_allclose(ang, se3.rotation_angle_deg(torch.from_numpy(rots)).numpy(), rtol=1e-12, atol=1e-10)
    np.testing.assert_allclose(ang, np.degrees(Rotation.from_matrix(rots).magnitude()), atol=1e-9)
    small = Rotation.from_rotvec([0, 1e-8, 0]).as_matrix()
    assert np.arccos(np.clip((np.trace(small) - 1) / 2, -1, 1)) == 0.0  # the textbook form reads 0 here
    assert float(rotation_angle_deg_np(small)) == pytest.approx(math.degrees(1e-8), rel=1e-6)
    assert float(rotation_angle_deg_np(1.001 * small)) == pytest.approx(math.degrees(1e-8), rel=2e-3)  # scaled


def test_nearest_rigid_np_projects_a_scaled_or_sheared_rotation_back_onto_it():
    R = Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix()
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = 1.001 * R, [1.0, 2.0, 3.0]
    out = se3.nearest_rigid_np(T)
    assert np.allclose(out[:3, :3], R, atol=1e-12) and np.allclose(out[:3, 3], [1, 2, 3]) and out[3, 3] == 1
    S = np.eye(3) + 1e-3 * np.array([[0, 1, 0], [1, 0, 0], [0, 0, 0]])  # symmetric shear: polar factor R S -> R
    T[:3, :3] = R @ S
    assert np.allclose(se3.nearest_rigid_np(T)[:3, :3], R, atol=1e-12)
    mirror = np.diag([-1.0, 1.0, 1.0, 1.0])
    assert np.linalg.det(se3.nearest_rigid_np(mirror)[:3, :3]) == pytest.approx(1.0)  # a rotation, not a reflection
    with pytest.raises(ValueError, match="4, 4"):
        se3.nearest_rigid_np(np.eye(3))


def test_opengl_opencv_is_involution_and_flips_axes():
    T = np.eye(4)
    T[:3, 3] = [1, 2, 3]
    cv = opengl_to_opencv(T)
    assert np.allclose(cv[:3, 1], [0, -1, 0]) and np.allclose(cv[:3, 2], [0, 0, -1])
    assert np.allclose(opencv_to_opengl(cv), T)
    assert np.allclose(cv[:3, 3], T[:3, 3])


def test_mean_pose_of_symmetric_poses_is_their_centre():
    axis = torch.tensor([0.3, -0.5, 0.8], dtype=torch.float64)
    axis = axis / axis.norm()
    centre = se3.se3_exp(torch.tensor([0.4, -0.1, 2.0, 0.2, 0.1, -0.3], dtype=torch.float64))

    def offset(sign: float) -> torch.Tensor:  # rotation of sign x 0.2 rad about `axis`, translation sign x t
        T = torch.eye(4, dtype=torch.float64)
        T[:3, :3] = se3.so3_exp(sign * 0.2 * axis)
        T[:3, 3] = sign * torch.tensor([0.01, 0.02, -0.03], dtype=torch.float64)
        return T

    m = se3.mean_pose(torch.stack([centre @ offset(1.0), centre @ offset(-1.0)]))
    torch.testing.assert_close(m, centre, atol=1e-12, rtol=0)
    one = centre @ offset(1.0)
    torch.testing.assert_close(se3.mean_pose(one[None]), one, atol=1e-12, rtol=0)
    # rotations about one axis by 0.1, 0.2, 0.6 rad: the chordal mean angle is atan2(sum sin, sum cos)
    angles = (0.1, 0.2, 0.6)
    Rs = [se3.se3_exp(torch.cat([torch.zeros(3, dtype=torch.float64), t * axis])) for t in angles]
    want = math.atan2(sum(math.sin(t) for t in angles), sum(math.cos(t) for t in angles))
    torch.testing.assert_close(se3.mean_pose(torch.stack(Rs))[:3, :3], se3.so3_exp(want * axis), atol=1e-12, rtol=0)
    with pytest.raises(ValueError, match="mean_pose"):
        se3.mean_pose(torch.zeros(0, 4, 4))
