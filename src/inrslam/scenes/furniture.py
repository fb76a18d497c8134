"""Furniture made of primitives, and a footprint placer that keeps tall things away from the camera loop.

All functions add parts to a `GeometryBuilder`; positions are world metres (z up, floor at 0); `yaw` in radians.
"""

from __future__ import annotations

import numpy as np

from inrslam.scenes.geometry import GeometryBuilder
from inrslam.scenes.textures import Material
from inrslam.scenes.trajectory import LoopPath, dense_loop


def _axes(yaw: float) -> tuple[np.ndarray, np.ndarray]:
    """Unit xy vectors (along, across) of a footprint rotated by `yaw`."""
    return np.array([np.cos(yaw), np.sin(yaw)]), np.array([-np.sin(yaw), np.cos(yaw)])


def table(b: GeometryBuilder, xy, w: float, d: float, h: float, top: Material, legs: Material,
          thick: float = 0.04, leg_r: float = 0.025) -> float:
    """Axis-aligned table (w along x, d along y, top surface at height h). Returns the top height."""
    b.add_box_on(xy, h - thick, (w, d, thick), top)
    for sx in (-1, 1):
        for sy in (-1, 1):
            b.add_post((xy[0] + sx * (w / 2 - 0.06), xy[1] + sy * (d / 2 - 0.06)), 0.0, h - thick, leg_r, legs, 12)
    return h


def chair(b: GeometryBuilder, xy, facing: float, seat: Material, legs: Material, size: float = 0.42,
          seat_h: float = 0.45, back_h: float = 0.45, leg_r: float = 0.015, thick: float = 0.04,
          spindle_r: float | None = None) -> float:
    """Chair whose sitter faces `facing` (radians); the back (a panel, or rods of radius `spindle_r`) is opposite.

    Returns the top height (metres).
    """
    f, s = _axes(facing)
    c = np.asarray(xy, dtype=np.float64)
    b.add_box_on(c, seat_h - thick, (size, size, thick), seat, yaw=facing)
    for a in (-1, 1):
        for bb in (-1, 1):
            p = c + (size / 2 - 0.03) * (a * f + bb * s)
            b.add_post(p, 0.0, seat_h - thick, leg_r, legs, 10)
    back = c - f * (size / 2 - 0.015)
    if spindle_r is None:
        b.add_box((back[0], back[1], seat_h + back_h / 2), (0.03, size, back_h), seat, yaw=facing)
    else:  # open back: thin vertical rods under a top rail
        for a in np.linspace(-1, 1, 4):
            p = back + a * (size / 2 - 0.03) * s
            b.add_post(p, seat_h, seat_h + back_h - 0.03, spindle_r, legs, 8)
        b.add_box((back[0], back[1], seat_h + back_h - 0.015), (0.03, size, 0.03), seat, yaw=facing)
    return seat_h + back_h


def shelf(b: GeometryBuilder, rng: np.random.Generator, xy, yaw: float, w: float, d: float, h: float, levels: int,
          wood: Material, items: list[Material], thick: float = 0.02, fill: float = 0.7) -> None:
    """Bookshelf: width w along `yaw`, depth d, `levels` boards, back panel on the +across side, items on boards."""
    e_w, e_d = _axes(yaw)
    c = np.asarray(xy, dtype=np.float64)
    for sgn in (-1, 1):
        p = c + sgn * (w / 2 - thick / 2) * e_w
        b.add_box_on(p, 0.0, (thick, d, h), wood, yaw=yaw)
    p = c + (d / 2 - thick / 2) * e_d
    b.add_box_on(p, 0.0, (w - 2 * thick, thick, h), wood, yaw=yaw)
    zs = np.linspace(0.05, h - thick, levels + 1)
    inner_w, inner_d = w - 2 * thick, d - thick
    for i, z in enumerate(zs):
        b.add_box_on(c - thick / 2 * e_d, z, (inner_w, inner_d, thick), wood, yaw=yaw)
        if i == len(zs) - 1:
            break
        space = zs[i + 1] - z - thick
        x = -inner_w / 2 + 0.03
        while True:
            iw = rng.uniform(0.06, 0.22)
            if x + iw > inner_w / 2 - 0.03:
                break
            if rng.random() < fill:
                ih = rng.uniform(0.35, 0.85) * space
                idp = rng.uniform(0.4, 0.8) * inner_d
                centre = c + (x + iw / 2) * e_w - thick / 2 * e_d
                mat = items[rng.integers(len(items))]
                kind = rng.random()
                if kind < 0.6:
                    b.add_box_on(centre, z + thick, (iw, idp, ih), mat, yaw=yaw)
                elif kind < 0.85:
                    r = min(iw, idp) / 2
                    b.add_post(centre, z + thick, z + thick + ih, r, mat, 16)
                else:
                    r = min(iw, idp, ih) / 2
                    b.add_sphere((centre[0], centre[1], z + thick + r), r, mat, 1)
            x += iw + rng.uniform(0.01, 0.05)


def poster(b: GeometryBuilder, wall: str, along: float, z_center: float, w: float, h: float, texture: str,
           contrast: float = 1.0) -> None:
    """A 1 cm thick picture on a wall ('-x', '+x', '-y', '+y'), image upright and unmirrored seen from inside.

    `along` is the centre coordinate along the wall (y for x-walls, x for y-walls).
    """
    room = b.room
    z_top = z_center + h / 2
    t = 0.01
    if wall in ("-x", "+x"):
        x = room[0, 0] + t / 2 if wall == "-x" else room[0, 1] - t / 2
        # seen from inside, image right is +y on the -x wall and -y on the +x wall
        u0, tu = (along - w / 2, w) if wall == "-x" else (along + w / 2, -w)
        mat = Material(texture, contrast=contrast, tile=(tu, h), offset=(0.0, u0, z_top))
        b.add_box((x, along, z_center), (t, w, h), mat)
    else:
        y = room[1, 0] + t / 2 if wall == "-y" else room[1, 1] - t / 2
        u0, tu = (along + w / 2, -w) if wall == "-y" else (along - w / 2, w)
        mat = Material(texture, contrast=contrast, tile=(tu, h), offset=(u0, 0.0, z_top))
        b.add_box((along, y, z_center), (w, t, h), mat)


def floor_lamp(b: GeometryBuilder, xy, h: float, metal: Material, shade_mat: Material) -> None:
    """Base disc, thin pole, cylindrical shade; total height h."""
    b.add_post(xy, 0.0, 0.03, 0.15, metal, 20)
    b.add_post(xy, 0.03, h - 0.25, 0.012, metal, 10)
    b.add_post(xy, h - 0.25, h, 0.17, shade_mat, 24)


def plant(b: GeometryBuilder, xy, pot: Material, leaves: Material, scale: float = 1.0) -> float:
    """Pot with a spherical crown. Returns the top height."""
    r = 0.12 * scale
    b.add_post(xy, 0.0, 0.28 * scale, r, pot, 20)
    rc = 0.22 * scale
    b.add_sphere((xy[0], xy[1], 0.28 * scale + rc * 0.9), rc, leaves, 2)
    return 0.28 * scale + 1.9 * rc


class Placer:
    """Non-overlapping axis-aligned footprints inside the room; tall objects keep away from the camera loop.

    An object is *low* when its top is at least `clearance` below the lowest camera height: it may stand
    under the loop. Otherwise its footprint must be at least `clearance` (xy) away from the loop.
    """

    def __init__(self, room: np.ndarray, path: LoopPath, clearance: float = 0.5, gap: float = 0.04):
        self.room = np.asarray(room, dtype=np.float64)
        self.loop_xy = dense_loop(path, 720)[:, :2]
        self.low_height = path.z_mid - path.z_amp - clearance
        self.clearance = clearance
        self.gap = gap
        self.rects: list[tuple[np.ndarray, np.ndarray]] = []

    def loop_distance(self, center, half) -> float:
        """Smallest xy distance from the loop to a footprint (metres)."""
        g = np.maximum(np.abs(self.loop_xy - np.asarray(center)) - np.asarray(half), 0.0)
        return float(np.sqrt((g * g).sum(1)).min())

    def free(self, center, half, height: float) -> bool:
        c, hf = np.asarray(center, dtype=np.float64), np.asarray(half, dtype=np.float64)
        if np.any(c - hf < self.room[:2, 0] + 0.01) or np.any(c + hf > self.room[:2, 1] - 0.01):
            return False
        for oc, oh in self.rects:
            if np.all(np.abs(c - oc) < hf + oh + self.gap):
                return False
        return height <= self.low_height or self.loop_distance(c, hf) >= self.clearance

    def take(self, center, half) -> None:
        self.rects.append((np.asarray(center, dtype=np.float64), np.asarray(half, dtype=np.float64)))

    def sample(self, rng: np.random.Generator, half, height: float, region=None, tries: int = 300):
        """Random free centre for a footprint with half sizes `half` (2,) and top `height`, or None.

        `region` (2, 2) [[xmin, xmax], [ymin, ymax]] limits the centre (default: the room).
        """
        half = np.asarray(half, dtype=np.float64)
        reg = self.room[:2] if region is None else np.asarray(region, dtype=np.float64)
        for _ in range(tries):
            lo, hi = reg[:, 0] + half, reg[:, 1] - half
            if np.any(lo > hi):
                return None
            c = rng.uniform(lo, hi)
            if self.free(c, half, height):
                self.take(c, half)
                return c
        return None

    def against_wall(self, rng: np.random.Generator, w: float, d: float, height: float, tries: int = 300):
        """Random free spot for a (w x d) object with its back to a wall.

        Returns (centre (2,), yaw) where yaw orients the width along the wall and the +across side to the wall,
        or None.
        """
        for _ in range(tries):
            wall = int(rng.integers(4))
            if wall in (0, 1):  # -x / +x walls: width along y
                half = np.array([d / 2, w / 2])
                x = self.room[0, 0] + d / 2 + 0.005 if wall == 0 else self.room[0, 1] - d / 2 - 0.005
                y = rng.uniform(self.room[1, 0] + w / 2, self.room[1, 1] - w / 2)
                c, yaw = np.array([x, y]), (np.pi / 2 if wall == 0 else -np.pi / 2)
            else:  # -y / +y walls: width along x
                half = np.array([w / 2, d / 2])
                y = self.room[1, 0] + d / 2 + 0.005 if wall == 2 else self.room[1, 1] - d / 2 - 0.005
                x = rng.uniform(self.room[0, 0] + w / 2, self.room[0, 1] - w / 2)
                c, yaw = np.array([x, y]), (np.pi if wall == 2 else 0.0)
            if self.free(c, half, height):
                self.take(c, half)
                return c, yaw
        return None
