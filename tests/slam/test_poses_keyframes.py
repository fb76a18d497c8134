import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from inrslam.geometry.se3 import compose_qt, matrix_to_quat, se3_exp
from inrslam.slam.config import PoseParam
from inrslam.slam.keyframes import KeyframeStore
from inrslam.slam.poses import PoseSet, constant_velocity, ray_poses, relative_pose, relative_trajectory


def random_poses(n, seed=0):
    rng = np.random.default_rng(seed)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.random(n, random_state=seed).as_matrix()
    T[:, :3, 3] = rng.normal(size=(n, 3))
    return torch.from_numpy(T)


@pytest.mark.parametrize("param", list(PoseParam))
def test_poseset_starts_at_initial_poses_and_is_differentiable(param):
    T = random_poses(5)
    ps = PoseSet(T, param)
    assert torch.allclose(ps.matrices(), T, atol=1e-12)
    loss = ps.matrices()[:, :3, 3].sum() + ps.matrices()[:, 0, 1].sum()
    loss.backward()
    grads = [p.grad for p in ps.parameters()]
    assert all(g is not None and torch.isfinite(g).all() and g.abs().sum() > 0 for g in grads)


def test_pose_parameterisations_gradcheck():
    """float64 gradcheck of both retractions used by tracking / BA."""
    T = random_poses(2)
    q = matrix_to_quat(T[:, :3, :3]).clone().requires_grad_()
    t = T[:, :3, 3].clone().requires_grad_()
    assert torch.autograd.gradcheck(compose_qt, (q, t))
    xi = (0.1 * torch.randn(2, 6, dtype=torch.float64)).requires_grad_()
    assert torch.autograd.gradcheck(lambda x: se3_exp(x) @ T, (xi,))
    xi0 = torch.zeros(2, 6, dtype=torch.float64, requires_grad=True)  # the SE3 start point
    assert torch.autograd.gradcheck(lambda x: se3_exp(x) @ T, (xi0,))


def test_poseset_se3_retraction_moves_by_twist():
    T = random_poses(1)
    ps = PoseSet(T, PoseParam.SE3)
    with torch.no_grad():
        ps.xi[0, :3] = torch.tensor([0.1, 0.0, 0.0], dtype=T.dtype)
    # a pure translation twist applied on the left shifts the camera centre in the world frame
    assert torch.allclose(ps.matrices()[0, :3, 3], T[0, :3, 3] + torch.tensor([0.1, 0, 0], dtype=T.dtype))


def test_constant_velocity_repeats_last_motion():
    T = random_poses(1)[0]
    delta = se3_exp(torch.tensor([0.01, 0.02, 0.0, 0.0, 0.01, 0.02], dtype=T.dtype))
    prev2, prev = T, delta @ T
    pred = constant_velocity(prev, prev2)
    assert torch.allclose(pred, delta @ delta @ T, atol=1e-12)
    assert torch.equal(constant_velocity(prev, None), prev)


def test_keyframe_store_sampling_and_state_roundtrip():
    store = KeyframeStore()
    for k, fid in enumerate([0, 5, 10]):
        n = 10 * (k + 1)
        store.add(fid, torch.full((n, 3), float(k)), torch.full((n, 3), 0.5), torch.full((n,), float(fid)))
    assert len(store) == 3 and store.n_rays == 60
    g = torch.Generator().manual_seed(0)
    slot, dirs, rgb, depth = store.sample(40, g)
    # each sampled ray carries its own keyframe's data
    assert torch.equal(dirs[:, 0], slot.float())
    assert torch.equal(depth, torch.tensor([0.0, 5.0, 10.0])[slot])
    assert slot.numel() == 40
    other = KeyframeStore()
    other.load_state_dict(store.state_dict())
    g1, g2 = torch.Generator().manual_seed(3), torch.Generator().manual_seed(3)
    a, b = store.sample(100, g1), other.sample(100, g2)
    assert all(torch.equal(x, y) for x, y in zip(a, b))


def test_keyframe_store_checkpoint_holds_only_the_rays_in_use(tmp_path):
    store = KeyframeStore()
    for k in range(5):  # 5 x 1000 rays: the buffers have grown (doubling) past the 5000 in use
        store.add(k, torch.rand(1000, 3), torch.rand(1000, 3), torch.rand(1000), torch.rand(1000))
    assert store.dirs.shape[0] > store.n_rays == 5000
    state = store.state_dict()
    for key in ("dirs", "rgb", "depth", "slot", "behind"):
        t = state[key]
        assert t.shape[0] == 5000 and t.untyped_storage().nbytes() == t.numel() * t.element_size(), key
    torch.save(state, tmp_path / "kf.pt")
    rays_bytes = 5000 * (3 + 3 + 1 + 1) * 4 + 5000 * 8  # dirs, rgb, depth, behind (float32), slot (int64)
    assert (tmp_path / "kf.pt").stat().st_size < 1.1 * rays_bytes
    other = KeyframeStore()
    other.load_state_dict(torch.load(tmp_path / "kf.pt"))
    assert all(torch.equal(getattr(other, k)[:5000], getattr(store, k)[:5000])
               for k in ("dirs", "rgb", "depth", "slot"))


def test_relative_trajectory_carries_non_keyframes_with_their_refined_keyframe():
    """Frames 1, 2 were tracked relative to keyframe 0, frame 4 relative to keyframe 3; bundle adjustment then moved
    the keyframes. Keyframes keep their refined pose, the others keep their tracked offset to it."""
    tracked = random_poses(5, seed=1).numpy()
    rel_kf = np.array([-1, 0, 0, -1, 3])
    rel = np.full((5, 4, 4), np.nan)
    for i in (1, 2):
        rel[i] = np.linalg.inv(tracked[0]) @ tracked[i]
    rel[4] = np.linalg.inv(tracked[3]) @ tracked[4]
    refined = tracked.copy()
    delta = random_poses(2, seed=2).numpy()
    refined[0] = delta[0] @ tracked[0]
    refined[3] = delta[1] @ tracked[3]
    out = relative_trajectory(refined, rel, rel_kf, keyframes=[0, 3])
    assert np.allclose(out[[0, 3]], refined[[0, 3]])  # keyframes unchanged
    for i, k in ((1, 0), (2, 0), (4, 3)):  # the keyframe's correction moves its frames rigidly
        assert np.allclose(out[i], delta[0 if k == 0 else 1] @ tracked[i])
        assert np.allclose(np.linalg.inv(out[k]) @ out[i], np.linalg.inv(tracked[k]) @ tracked[i])
    # without refinement the relative trajectory is the absolute one
    assert np.allclose(relative_trajectory(tracked, rel, rel_kf, [0, 3]), tracked)


def test_relative_trajectory_in_the_original_form_applies_the_correction_in_the_frames_own_camera():
    """Keyframe 0 at the origin, frame 1 one metre along x; bundle adjustment turns the keyframe by 90 degrees about
    z. Held rigid (inrslam), frame 1 swings round to (0, 1, 0); in the original form (Co-SLAM), rel = c2w_1 c2w_0^-1
    is a pure translation, so frame 1 stays at (1, 0, 0) and only turns."""
    kf, frame = np.eye(4), np.eye(4)
    frame[0, 3] = 1.0
    turned = np.eye(4)
    turned[:3, :3] = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    tracked = np.stack([kf, frame])
    for faithful, centre in ((False, [0.0, 1.0, 0.0]), (True, [1.0, 0.0, 0.0])):
        rel = np.stack([np.eye(4), relative_pose(torch.from_numpy(kf), torch.from_numpy(frame), faithful).numpy()])
        out = relative_trajectory(np.stack([turned, frame]), rel, np.array([-1, 0]), [0], faithful)
        np.testing.assert_allclose(out[1][:3, 3], centre, atol=1e-12)
        np.testing.assert_allclose(out[1][:3, :3], turned[:3, :3], atol=1e-12)  # the frame turns with it either way
        assert np.allclose(relative_trajectory(tracked, rel, np.array([-1, 0]), [0], faithful), tracked)


def test_ray_poses_gradient_is_the_same_on_every_run():
    """Mapping gathers a pose per ray; its gradient sums thousands of rays per pose and must not depend on thread
    timing (``mats[slots]`` gave a different gradient on each of 50 runs here, 2 threads)."""
    g = torch.Generator().manual_seed(0)
    mats = torch.randn(8, 4, 4, generator=g, requires_grad=True)
    slots = torch.randint(0, 8, (8192,), generator=g)
    cot = torch.randn(8192, 4, 4, generator=g)
    out = ray_poses(mats, slots)
    assert torch.equal(out, mats.detach()[slots])
    grads = set()
    for _ in range(20):
        mats.grad = None
        (ray_poses(mats, slots) * cot).sum().backward()
        grads.add(mats.grad.numpy().tobytes())
    assert len(grads) == 1
    expected = torch.zeros(8, 4, 4, dtype=torch.float64).index_add_(0, slots, cot.double())
    torch.testing.assert_close(mats.grad.double(), expected, rtol=1e-5, atol=1e-4)
