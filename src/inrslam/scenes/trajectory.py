"""Smooth hand-held-like camera paths inside a room: a wobbly closed loop, looking inward with slow yaw / pitch /
roll oscillations. Poses are camera-to-world, OpenCV axes (x right, y down, z forward), world z up.

Position: the loop point at arc length s_i (metres, wrapped), with s_i = s_0 + dir * motion_scale * sum_{k<i} v_k
and per-frame speed v_k = speed * (1 + speed_var * sin(2 pi k / speed_period + phase)).
Viewing direction: yaw = heading towards `look_center` + yaw_amp * sin(2 pi d / yaw_period + phase), pitch and
roll alike, where d = |s_i - s_0| is the distance travelled, so rotation per frame also scales with motion_scale.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class LoopPath:
    """Parameters of a camera loop (all metres / radians)."""

    center: tuple[float, float]  # loop centre (x, y)
    radii: tuple[float, float]  # ellipse half-axes along x and y
    harmonics: tuple[tuple[float, int, float], ...]  # radial wobble terms (relative amplitude, order, phase)
    z_mid: float  # mean camera height
    z_amp: float  # height oscillation amplitude
    z_order: int  # height oscillations per loop
    z_phase: float
    look_center: tuple[float, float, float]  # point the camera looks around
    yaw_amp: float = 0.5  # yaw oscillation around the inward heading
    yaw_period: float = 5.0  # metres travelled per yaw oscillation
    yaw_phase: float = 0.0
    pitch_mean: float = -0.38  # negative = looking down
    pitch_amp: float = 0.12
    pitch_period: float = 3.7
    pitch_phase: float = 0.0
    roll_amp: float = 0.05
    roll_period: float = 4.3
    roll_phase: float = 0.0
    speed: float = 0.009  # mean metres per frame at motion_scale = 1
    speed_var: float = 0.35  # relative speed oscillation
    speed_period: float = 90.0  # frames per speed oscillation
    speed_phase: float = 0.0
    start: float = 0.0  # start position as a fraction of the loop
    direction: int = 1  # +1 counter-clockwise, -1 clockwise


def loop_points(path: LoopPath, theta: np.ndarray) -> np.ndarray:
    """(N,) loop angles (radians) -> (N, 3) camera positions, metres."""
    r = np.ones_like(theta)
    for amp, order, phase in path.harmonics:
        r = r + amp * np.cos(order * theta + phase)
    x = path.center[0] + path.radii[0] * r * np.cos(theta)
    y = path.center[1] + path.radii[1] * r * np.sin(theta)
    z = path.z_mid + path.z_amp * np.sin(path.z_order * theta + path.z_phase)
    return np.stack([x, y, z], axis=1)


def dense_loop(path: LoopPath, n: int = 2048) -> np.ndarray:
    """(n, 3) evenly spaced-in-angle samples of the closed loop (for clearance checks and arc length)."""
    return loop_points(path, np.linspace(0.0, 2 * np.pi, n, endpoint=False))


def look_rotation(forward: np.ndarray, roll: np.ndarray | float = 0.0, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world rotations in OpenCV axes.

    Args:
        forward: (N, 3) viewing directions (camera +z), any length, not parallel to `up`.
        roll: (N,) or scalar, radians about the viewing direction (positive turns the image clockwise).
        up: world up vector.
    Returns:
        (N, 3, 3) rotations with columns (right, down, forward).
    """
    f = forward / np.linalg.norm(forward, axis=-1, keepdims=True)
    right = np.cross(f, np.asarray(up, dtype=np.float64))
    right /= np.linalg.norm(right, axis=-1, keepdims=True)
    down = np.cross(f, right)
    c, s = np.cos(roll), np.sin(roll)
    c, s = np.broadcast_to(c, f.shape[:-1])[..., None], np.broadcast_to(s, f.shape[:-1])[..., None]
    right, down = c * right + s * down, -s * right + c * down
    return np.stack([right, down, f], axis=-1)


def camera_poses(path: LoopPath, frames: int, motion_scale: float = 1.0) -> np.ndarray:
    """(frames, 4, 4) float64 camera-to-world poses along `path` (OpenCV axes)."""
    theta = np.linspace(0.0, 2 * np.pi, 4097)
    pts = loop_points(path, theta)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
    length = arc[-1]
    k = np.arange(frames, dtype=np.float64)
    v = path.speed * (1.0 + path.speed_var * np.sin(2 * np.pi * k / path.speed_period + path.speed_phase))
    travelled = motion_scale * np.concatenate([[0.0], np.cumsum(v)[:-1]])
    s = np.mod(path.start * length + path.direction * travelled, length)
    pos = loop_points(path, np.interp(s, arc, theta))

    to_c = np.asarray(path.look_center[:2]) - pos[:, :2]
    yaw = np.arctan2(to_c[:, 1], to_c[:, 0]) + path.yaw_amp * np.sin(2 * np.pi * travelled / path.yaw_period + path.yaw_phase)
    pitch = path.pitch_mean + path.pitch_amp * np.sin(2 * np.pi * travelled / path.pitch_period + path.pitch_phase)
    roll = path.roll_amp * np.sin(2 * np.pi * travelled / path.roll_period + path.roll_phase)
    fwd = np.stack([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)], axis=1)

    poses = np.tile(np.eye(4), (frames, 1, 1))
    poses[:, :3, :3] = look_rotation(fwd, roll)
    poses[:, :3, 3] = pos
    return poses


def random_loop(rng: np.random.Generator, center, radii, z_range, look_center, **overrides) -> LoopPath:
    """A `LoopPath` with seeded wobble, phases, start and direction.

    Args:
        rng: generator (consumed deterministically).
        center: (2,) loop centre; radii: (2,) half-axes, metres; z_range: (zmin, zmax) camera heights.
        look_center: (3,) point the camera looks around.
        overrides: any other `LoopPath` field.
    """
    harmonics = ((rng.uniform(0.03, 0.07), 2, rng.uniform(0, 2 * np.pi)), (rng.uniform(0.0, 0.03), 3, rng.uniform(0, 2 * np.pi)))
    kw = dict(
        center=tuple(map(float, center)),
        radii=tuple(map(float, radii)),
        harmonics=tuple((float(a), int(o), float(p)) for a, o, p in harmonics),
        z_mid=float(np.mean(z_range)),
        z_amp=float(z_range[1] - z_range[0]) / 2,
        z_order=int(rng.integers(1, 4)),
        z_phase=float(rng.uniform(0, 2 * np.pi)),
        look_center=tuple(map(float, look_center)),
        yaw_phase=float(rng.uniform(0, 2 * np.pi)),
        pitch_phase=float(rng.uniform(0, 2 * np.pi)),
        roll_phase=float(rng.uniform(0, 2 * np.pi)),
        speed_phase=float(rng.uniform(0, 2 * np.pi)),
        start=float(rng.uniform(0, 1)),
        direction=int(rng.choice([-1, 1])),
    )
    kw.update(overrides)
    return LoopPath(**kw)

