"""The built-in scene layouts: geometry + camera loop, each deterministic from a seed.

World: metres, z up, floor at z = 0, room centred on the origin in xy. Every builder keeps the camera loop at
least 0.4 m from every surface (tall objects are placed >= 0.5 m (xy) from the loop, low ones >= 0.5 m below
the lowest camera height; checked exactly in the tests).
"""

from __future__ import annotations

import dataclasses
import zlib
from dataclasses import dataclass
from typing import Callable

import numpy as np

from inrslam.registry import Registry
from inrslam.scenes import furniture as fur
from inrslam.scenes.geometry import GeometryBuilder, SceneGeometry
from inrslam.scenes.textures import Material
from inrslam.scenes.trajectory import LoopPath, dense_loop, random_loop


@dataclass
class SceneLayout:
    """What a scene builder returns."""

    name: str
    geometry: SceneGeometry
    path: LoopPath
    default_frames: int


SceneBuilder = Callable[[int], SceneLayout]
SCENES: Registry[SceneBuilder] = Registry("scene")

DEFAULT_FRAMES = {"room": 200, "cluttered": 300, "thin": 200, "handheld": 200, "loop": 320, "symmetric": 320}
LOOP_COVER = 1.06
"""Loops per sequence of the `loop` and `symmetric` scenes at their default length: once around, and a little on."""
"""Sequence length of each scene when `SceneConfig.frames` is 0."""


def scene_rng(seed: int, name: str) -> np.random.Generator:
    """Generator for a scene's layout and path, independent across scene names."""
    return np.random.default_rng([int(seed), zlib.crc32(name.encode())])


def _pick(rng: np.random.Generator, items: list):
    return items[int(rng.integers(len(items)))]


def _colour(rng: np.random.Generator, lo: float = 0.25, hi: float = 0.9) -> tuple[float, float, float]:
    return tuple(float(c) for c in rng.uniform(lo, hi, 3))


# (texture, width / height) of the photographs used as posters
_POSTERS = [("astronaut", 1.0), ("chelsea", 451 / 300), ("coffee", 600 / 400), ("rocket", 640 / 427),
            ("hubble", 1000 / 872), ("ihc", 1.0), ("camera", 1.0)]


def _room_box(rng: np.random.Generator, size: tuple[float, float, float],
              jitter: tuple[float, float, float]) -> np.ndarray:
    """(3, 2) extents of a room of about `size` (W, D, H) m, each jittered by +-`jitter`; centred in xy, floor at 0."""
    W, D, H = (s + rng.uniform(-j, j) for s, j in zip(size, jitter))
    return np.array([[-W / 2, W / 2], [-D / 2, D / 2], [0.0, H]])


# the potted plant and the floor lamp look the same in every scene
_POT = Material("brick", tint=(0.7, 0.4, 0.3), contrast=0.5, tile=(0.3, 0.3))
_LEAVES = Material("grass", tint=(0.35, 0.6, 0.3), contrast=1.2, tile=(0.4, 0.4))
_SHADE = Material("page", tint=(0.95, 0.9, 0.75), contrast=0.4, tile=(0.3, 0.3))


def _textured_walls(rng: np.random.Generator) -> list[Material]:
    """Four wall materials from a palette of textured finishes, in seeded order."""
    palette = [
        Material("brick", tint=(0.78, 0.5, 0.4), contrast=1.0, tile=(1.2, 1.2)),
        Material("moon", tint=(0.85, 0.8, 0.7), contrast=1.6, tile=(1.3, 1.3)),
        Material("camera", tint=(0.7, 0.75, 0.82), contrast=0.6, tile=(2.0, 2.0)),
        Material("gravel", tint=(0.78, 0.84, 0.72), contrast=0.9, tile=(1.0, 1.0)),
        Material("page", tint=(0.9, 0.86, 0.78), contrast=0.7, tile=(0.9, 0.9)),
    ]
    order = rng.permutation(len(palette))[:4]
    return [palette[i] for i in order]


def _wood(rng: np.random.Generator) -> Material:
    t = rng.uniform(0.85, 1.15)
    return Material("grass", tint=(0.62 * t, 0.44 * t, 0.27 * t), contrast=0.8, tile=(0.6, 0.6))


def _object_materials(rng: np.random.Generator) -> list[Material]:
    """Textures for small objects (boxes, books, balls, pots)."""
    return [
        Material("text", tint=(0.78, 0.62, 0.42), contrast=0.8, tile=(0.35, 0.35)),
        Material("coins", tint=(0.8, 0.8, 0.85), contrast=1.2, tile=(0.3, 0.3)),
        Material("colorwheel", tile=(0.25, 0.25)),
        Material("coffee", tile=(0.4, 0.4)),
        Material("chelsea", tile=(0.4, 0.4)),
        Material("rocket", tile=(0.5, 0.5)),
        Material("gravel", tint=_colour(rng), contrast=1.0, tile=(0.3, 0.3)),
        Material("brick", tint=_colour(rng), contrast=0.8, tile=(0.4, 0.4)),
        Material("moon", tint=_colour(rng), contrast=1.5, tile=(0.4, 0.4)),
    ]


def _place_posters(b: GeometryBuilder, pl: fur.Placer, rng: np.random.Generator, n: int, z_center: float,
                   width: tuple[float, float]) -> None:
    """Up to `n` posters on free wall spans (footprints registered with the placer)."""
    choices = rng.permutation(len(_POSTERS))
    room = b.room
    for k in choices[:n]:
        tex, aspect = _POSTERS[k]
        w = rng.uniform(*width)
        h = w / aspect
        for _ in range(50):
            wall = _pick(rng, ["-x", "+x", "-y", "+y"])
            axis = 1 if wall in ("-x", "+x") else 0
            along = rng.uniform(room[axis, 0] + w / 2 + 0.1, room[axis, 1] - w / 2 - 0.1)
            other = 0 if axis == 1 else 1
            depth_c = room[other, 0] + 0.005 if wall[0] == "-" else room[other, 1] - 0.005
            c = np.zeros(2)
            c[axis], c[other] = along, depth_c
            half = np.zeros(2)
            half[axis], half[other] = w / 2, 0.005
            if pl.free(c, half, 99.0):  # posters are tall: never near the loop
                pl.take(c, half)
                fur.poster(b, wall, along, z_center, w, h, tex)
                break


def _small_items(b: GeometryBuilder, rng: np.random.Generator, center, half, z0: float, max_h: float, n: int,
                 mats: list[Material]) -> None:
    """`n` small objects (boxes, cylinders, spheres) resting on the surface at height z0 within a rectangle."""
    placed: list[tuple[np.ndarray, float]] = []
    for _ in range(n * 10):
        if len(placed) >= n:
            break
        r = rng.uniform(0.04, 0.1)
        p = rng.uniform(np.asarray(center) - np.asarray(half) + r + 0.03, np.asarray(center) + np.asarray(half) - r - 0.03)
        if any(np.linalg.norm(p - q) < r + rq + 0.03 for q, rq in placed):
            continue
        placed.append((p, r))
        mat = _pick(rng, mats)
        kind = rng.random()
        h = rng.uniform(0.05, max_h)
        if kind < 0.4:
            b.add_box_on(p, z0, (1.4 * r, 1.4 * r, h), mat, yaw=rng.uniform(0, np.pi))
        elif kind < 0.75:
            b.add_post(p, z0, z0 + h, r * 0.8, mat, 20)
        else:
            rs = min(r, max_h / 2)
            b.add_sphere((p[0], p[1], z0 + rs), rs, mat, 2)


def _box_stack(b: GeometryBuilder, pl: fur.Placer, rng: np.random.Generator, mats: list[Material], size=(0.2, 0.55),
               max_height: float = 0.9, levels: int = 2) -> bool:
    """A stack of 1..levels boxes on the floor (each smaller than the one below). Returns False if no space."""
    w, d = rng.uniform(*size, 2)
    hs = [rng.uniform(0.15, 0.45) for _ in range(int(rng.integers(1, levels + 1)))]
    total = sum(hs)
    if total > max_height:
        hs = [h * max_height / total for h in hs]
        total = max_height
    c = pl.sample(rng, (w / 2, d / 2), total)
    if c is None:
        return False
    z = 0.0
    for h in hs:
        b.add_box_on(c, z, (w, d, h), _pick(rng, mats))
        z += h
        w, d = w * rng.uniform(0.6, 0.9), d * rng.uniform(0.6, 0.9)
    return True


@SCENES.register("room", help="small furnished room 4 x 3.5 x 2.6 m: table, chairs, shelf, boxes, posters (default)")
def build_room(seed: int) -> SceneLayout:
    """A ~4 x 3.5 x 2.6 m room with a table and chairs in the middle, a bookshelf, a cabinet, boxes, plant, lamp."""
    return _furnished_room(seed, "room", dict(yaw_amp=0.4, yaw_period=6.0))


@SCENES.register("handheld", help="room-like, hand-held motion: 3-5 cm / ~2.6 deg per frame, wall views, depth noise "
                                  "(1 % of depth at 2.5 m), 5 % holes")
def build_handheld(seed: int) -> SceneLayout:
    """A furnished room like `room`, with a faster, swinging camera: ~3.5 cm per frame on average (+-50 %), yaw
    swinging +-80 degrees around the inward heading so that some views face a wall; sensor noise by default."""
    return _furnished_room(seed, "handheld", dict(speed=0.035, speed_var=0.5, speed_period=60.0, yaw_amp=0.9,
                                                 yaw_period=6.0, pitch_amp=0.15, roll_amp=0.05))


@SCENES.register("loop", help="room-like, once around and back to the start in 320 frames (~1.8 cm / frame, faster "
                              "segments, wall views, depth noise and holes): the loop-closure scene")
def build_loop(seed: int) -> SceneLayout:
    """A furnished room like `room`; the camera swings like `handheld`'s at half its speed and goes once around
    the loop (LOOP_COVER loops in the default 320 frames), so the end revisits the start."""
    layout = _furnished_room(seed, "loop", dict(speed_var=0.4, speed_period=80.0, yaw_amp=0.8, yaw_period=5.0,
                                               pitch_amp=0.15, roll_amp=0.05))
    return _once_around(layout)


@SCENES.register("symmetric", help="square room with four identical walls, corners and posters (4-fold symmetric), "
                                   "once around in 320 frames: the false-loop scene")
def build_symmetric(seed: int) -> SceneLayout:
    """A 4 x 4 x 2.6 m room, symmetric under quarter turns: the same wall finish and poster on every wall, the same
    box stack in every corner, a square table in the middle. Every view has a twin a quarter turn away, so a loop
    detector that trusted appearance alone would close false loops."""
    rng = scene_rng(seed, "symmetric")
    room = np.array([[-2.0, 2.0], [-2.0, 2.0], [0.0, 2.6]])
    wall = Material("brick", tint=(0.78, 0.5, 0.4), contrast=1.0, tile=(1.0, 1.0))
    b = GeometryBuilder(room)
    b.add_room(floor=Material("gravel", tint=(0.56, 0.46, 0.36), contrast=1.2, tile=(0.8, 0.8)),
               ceiling=Material("gravel", tint=(0.92, 0.92, 0.9), contrast=0.15, tile=(1.5, 1.5)),
               walls=[wall] * 4)
    box = Material("coins", tint=(0.8, 0.8, 0.85), contrast=1.2, tile=(0.3, 0.3))
    top = Material("colorwheel", tile=(0.25, 0.25))
    for sx in (-1, 1):
        for sy in (-1, 1):
            b.add_box_on((1.6 * sx, 1.6 * sy), 0.0, (0.5, 0.5, 0.6), box)
            b.add_box_on((1.6 * sx, 1.6 * sy), 0.6, (0.3, 0.3, 0.3), top)
    b.add_box_on((0.0, 0.0), 0.0, (0.8, 0.8, 0.75), _wood(rng))
    for w in ("-x", "+x", "-y", "+y"):
        fur.poster(b, w, 0.0, 1.5, 0.7, 0.7, "astronaut")
    path = random_loop(rng, (0.0, 0.0), (1.0, 1.0), (1.4, 1.75), (0.0, 0.0, 0.8), speed_var=0.4, speed_period=80.0,
                       yaw_amp=0.6, yaw_period=5.0)
    return _once_around(SceneLayout("symmetric", b.build(), path, default_frames=DEFAULT_FRAMES["symmetric"]))


def _once_around(layout: SceneLayout) -> SceneLayout:
    """`layout` with its camera speed set so that the default number of frames covers LOOP_COVER loops."""
    pts = dense_loop(layout.path)
    length = float(np.linalg.norm(np.diff(np.vstack([pts, pts[:1]]), axis=0), axis=1).sum())
    speed = LOOP_COVER * length / (layout.default_frames - 1)
    return dataclasses.replace(layout, path=dataclasses.replace(layout.path, speed=speed))


def _furnished_room(seed: int, name: str, path_kw: dict) -> SceneLayout:
    rng = scene_rng(seed, name)
    room = _room_box(rng, (4.0, 3.5, 2.6), (0.1, 0.1, 0.04))
    centre = rng.uniform(-0.08, 0.08, 2)
    path = random_loop(rng, centre, (rng.uniform(0.95, 1.05), rng.uniform(0.68, 0.76)), (1.4, 1.75), (*centre, 0.8),
                       **path_kw)
    b = GeometryBuilder(room)
    b.add_room(floor=Material("gravel", tint=(0.56, 0.46, 0.36), contrast=1.2, tile=(0.8, 0.8)),
               ceiling=Material("gravel", tint=(0.92, 0.92, 0.9), contrast=0.15, tile=(1.5, 1.5)),
               walls=_textured_walls(rng))
    pl = fur.Placer(room, path)
    mats = _object_materials(rng)
    metal = Material("flat", tint=(0.22, 0.22, 0.25))

    # rug, table and chairs in the middle (all below the camera loop)
    rw, rd = rng.uniform(1.8, 2.2), rng.uniform(1.3, 1.6)
    b.add_box_on(centre, 0.0, (rw, rd, 0.01), Material("coffee", tile=(rw, rd), offset=(centre[0] - rw / 2, centre[1] - rd / 2, 0)))
    tw, td = rng.uniform(1.0, 1.2), rng.uniform(0.65, 0.8)
    top = fur.table(b, centre, tw, td, 0.75, _wood(rng), metal)
    pl.take(centre, (tw / 2 + 0.3, td / 2 + 0.3))
    seat = Material("gravel", tint=_colour(rng), contrast=0.9, tile=(0.3, 0.3))
    slots = [((tw / 2 + 0.12, 0), np.pi), ((-tw / 2 - 0.12, 0), 0.0), ((0, td / 2 + 0.12), -np.pi / 2), ((0, -td / 2 - 0.12), np.pi / 2)]
    for k in rng.permutation(4)[: int(rng.integers(2, 5))]:
        off, facing = slots[k]
        jitter = rng.uniform(-0.15, 0.15) * (np.array([0, 1]) if off[1] == 0 else np.array([1, 0]))
        fur.chair(b, centre + np.array(off) + jitter, facing + rng.uniform(-0.15, 0.15), seat, metal, back_h=0.42)
    _small_items(b, rng, centre, (tw / 2 - 0.05, td / 2 - 0.05), top, min(0.2, pl.low_height - top), int(rng.integers(3, 6)), mats)

    # against the walls: a tall bookshelf and a low cabinet with things on top
    spot = pl.against_wall(rng, 0.9, 0.32, 1.8)
    if spot is not None:
        fur.shelf(b, rng, spot[0], spot[1], 0.9, 0.32, 1.8, 4, _wood(rng), mats)
    spot = pl.against_wall(rng, 1.0, 0.45, 0.8)
    if spot is not None:
        cab = Material("camera", tint=(0.85, 0.8, 0.7), contrast=0.7, tile=(0.8, 0.8))
        b.add_box_on(spot[0], 0.0, (1.0, 0.45, 0.8), cab, yaw=spot[1])
        half = (0.4, 0.15) if abs(np.cos(spot[1])) > 0.5 else (0.15, 0.4)
        _small_items(b, rng, spot[0], half, 0.8, 0.3, 3, mats)

    for _ in range(int(rng.integers(2, 4))):
        _box_stack(b, pl, rng, mats[:2] + mats[6:])
    c = pl.sample(rng, (0.23, 0.23), 0.7)
    if c is not None:
        fur.plant(b, c, _POT, _LEAVES)
    c = pl.sample(rng, (0.18, 0.18), 1.6)
    if c is not None:
        fur.floor_lamp(b, c, 1.6, metal, _SHADE)
    _place_posters(b, pl, rng, int(rng.integers(2, 4)), 1.55, (0.6, 0.8))
    return SceneLayout(name, b.build(), path, default_frames=DEFAULT_FRAMES[name])


@SCENES.register("cluttered", help="large cluttered room 7 x 5 x 3 m with many objects of varied sizes")
def build_cluttered(seed: int) -> SceneLayout:
    """A ~7 x 5 x 3 m storage / living room: shelves, cabinets, tables, chairs, box stacks, barrels, balls."""
    rng = scene_rng(seed, "cluttered")
    room = _room_box(rng, (7.0, 5.0, 3.0), (0.15, 0.15, 0.05))
    centre = rng.uniform(-0.15, 0.15, 2)
    path = random_loop(rng, centre, (rng.uniform(1.9, 2.1), rng.uniform(1.15, 1.3)), (1.4, 1.85), (*centre, 0.7),
                       yaw_amp=0.45, yaw_period=6.0)
    b = GeometryBuilder(room)
    b.add_room(floor=Material("brick", tint=(0.55, 0.5, 0.45), contrast=0.9, tile=(1.0, 1.0)),
               ceiling=Material("gravel", tint=(0.9, 0.9, 0.88), contrast=0.2, tile=(1.5, 1.5)),
               walls=_textured_walls(rng))
    pl = fur.Placer(room, path)
    mats = _object_materials(rng)
    metal = Material("flat", tint=(0.25, 0.25, 0.28))

    tw, td = rng.uniform(1.4, 1.7), rng.uniform(0.8, 0.95)
    top = fur.table(b, centre, tw, td, 0.75, _wood(rng), metal)
    pl.take(centre, (tw / 2 + 0.3, td / 2 + 0.3))
    seat = Material("gravel", tint=_colour(rng), contrast=0.9, tile=(0.3, 0.3))
    for sx in (-1, 1):
        fur.chair(b, centre + (sx * (tw / 2 + 0.12), 0), 0.0 if sx < 0 else np.pi, seat, metal, back_h=0.42)
        for a in (-0.3, 0.3):
            fur.chair(b, centre + (a * tw + rng.uniform(-0.05, 0.05), sx * (td / 2 + 0.12)), -sx * np.pi / 2, seat, metal,
                      back_h=0.42)
    _small_items(b, rng, centre, (tw / 2 - 0.05, td / 2 - 0.05), top, min(0.25, pl.low_height - top), int(rng.integers(5, 9)), mats)

    for _ in range(2):
        w, h = float(rng.uniform(0.8, 1.2)), float(rng.uniform(1.8, 2.2))
        spot = pl.against_wall(rng, w, 0.35, h)
        if spot is not None:
            fur.shelf(b, rng, spot[0], spot[1], w, 0.35, h, int(rng.integers(4, 6)), _wood(rng), mats)
    for _ in range(2):
        h = float(rng.uniform(0.8, 2.0))
        spot = pl.against_wall(rng, rng.uniform(0.5, 1.0), rng.uniform(0.4, 0.6), h)
        if spot is not None:
            half = pl.rects[-1][1]
            ext = (2 * half[0], 2 * half[1], h)
            b.add_box_on(spot[0], 0.0, ext, Material("camera", tint=_colour(rng, 0.5, 0.95), contrast=0.7, tile=(0.9, 0.9)))
    # a second, small table with two chairs
    c = pl.sample(rng, (0.45, 0.45), 0.75)
    if c is not None:
        t2 = fur.table(b, c, 0.6, 0.6, 0.72, _wood(rng), metal)
        _small_items(b, rng, c, (0.25, 0.25), t2, 0.08, 2, mats)
    for _ in range(int(rng.integers(10, 16))):
        _box_stack(b, pl, rng, mats, size=(0.12, 0.65), max_height=1.6, levels=3)
    for _ in range(int(rng.integers(4, 8))):  # barrels and bins
        r, h = rng.uniform(0.1, 0.3), rng.uniform(0.2, 0.9)
        c = pl.sample(rng, (r, r), h)
        if c is not None:
            b.add_post(c, 0.0, h, r, _pick(rng, mats), 24)
    for _ in range(int(rng.integers(4, 8))):  # balls
        r = rng.uniform(0.05, 0.25)
        c = pl.sample(rng, (r, r), 2 * r)
        if c is not None:
            b.add_sphere((c[0], c[1], r), r, _pick(rng, mats), 2)
    for _ in range(int(rng.integers(2, 4))):
        s = rng.uniform(0.8, 1.3)
        c = pl.sample(rng, (0.25 * s, 0.25 * s), 0.7 * s)
        if c is not None:
            fur.plant(b, c, _POT, _LEAVES, s)
    c = pl.sample(rng, (0.18, 0.18), 1.7)
    if c is not None:
        fur.floor_lamp(b, c, 1.7, metal, _SHADE)
    _place_posters(b, pl, rng, int(rng.integers(3, 5)), 1.7, (0.7, 1.0))
    return SceneLayout("cluttered", b.build(), path, default_frames=DEFAULT_FRAMES["cluttered"])


@SCENES.register("thin", help="thin structures (poles, railing, 2-3 cm panels, spindly chairs) and low-texture walls")
def build_thin(seed: int) -> SceneLayout:
    """A ~5 x 4 x 2.7 m room with near-uniform walls, floor-to-ceiling poles, a railing, thin panels and chairs."""
    rng = scene_rng(seed, "thin")
    room = _room_box(rng, (5.0, 4.0, 2.7), (0.1, 0.1, 0.04))
    H = float(room[2, 1])
    centre = rng.uniform(-0.1, 0.1, 2)
    path = random_loop(rng, centre, (rng.uniform(1.3, 1.4), rng.uniform(0.9, 1.0)), (1.35, 1.75), (*centre, 0.8))
    base = np.array(rng.uniform(0.75, 0.9, 3))

    def plain() -> Material:  # near-uniform paint: +-2% variation
        tint = np.clip(base + rng.uniform(-0.04, 0.04, 3), 0, 1)
        return Material("gravel", tint=tuple(float(t) for t in tint), contrast=0.06, tile=(1.5, 1.5))

    b = GeometryBuilder(room)
    b.add_room(floor=Material("gravel", tint=(0.5, 0.5, 0.52), contrast=0.8, tile=(1.0, 1.0)),
               ceiling=plain(), walls=[plain() for _ in range(4)])
    pl = fur.Placer(room, path)
    mats = _object_materials(rng)
    metal = Material("flat", tint=(0.2, 0.2, 0.22))
    chrome = Material("flat", tint=(0.6, 0.6, 0.62))

    # thin table (2 cm top, thin legs) with spindly chairs, below the loop
    top = fur.table(b, centre, 0.9, 0.6, 0.72, _wood(rng), metal, thick=0.02, leg_r=0.012)
    pl.take(centre, (0.75, 0.6))
    seat = Material("flat", tint=_colour(rng))
    for sx in (-1, 1):
        fur.chair(b, centre + (sx * 0.57, rng.uniform(-0.1, 0.1)), 0.0 if sx < 0 else np.pi, seat, metal, back_h=0.36,
                  leg_r=0.01, thick=0.02, spindle_r=0.008)
    _small_items(b, rng, centre, (0.4, 0.25), top, 0.12, 3, mats)

    # floor-to-ceiling poles
    for _ in range(int(rng.integers(3, 6))):
        r = rng.uniform(0.012, 0.02)
        c = pl.sample(rng, (r, r), H)
        if c is not None:
            b.add_post(c, 0.0, H, r, _pick(rng, [metal, chrome]), 12)
    # a railing along a wall: posts every ~0.4 m, top and middle rails
    length = rng.uniform(1.5, 2.5)
    for _ in range(100):
        wall = int(rng.integers(4))
        axis = 1 if wall < 2 else 0  # the railing runs along y on x-walls
        other = 1 - axis
        along = rng.uniform(room[axis, 0] + length / 2 + 0.05, room[axis, 1] - length / 2 - 0.05)
        off = room[other, 0] + 0.25 if wall % 2 == 0 else room[other, 1] - 0.25
        c, half = np.zeros(2), np.zeros(2)
        c[axis], c[other], half[axis], half[other] = along, off, length / 2, 0.02
        if pl.free(c, half, 1.02):
            pl.take(c, half)
            n_posts = int(np.ceil(length / 0.4)) + 1
            pts = [c.copy() for _ in range(n_posts)]
            for i, p in enumerate(pts):
                p[axis] = along - length / 2 + i * length / (n_posts - 1)
                b.add_post(p, 0.0, 1.0, 0.015, metal, 10)
            e0, e1 = c.copy(), c.copy()
            e0[axis], e1[axis] = along - length / 2 - 0.02, along + length / 2 + 0.02
            b.add_cylinder((*e0, 1.0), (*e1, 1.0), 0.02, chrome, 12)
            b.add_cylinder((*e0, 0.5), (*e1, 0.5), 0.01, chrome, 10)
            break
    # free-standing thin panels (2-3 cm)
    panel_mats = [Material("camera", tint=(0.8, 0.8, 0.8), contrast=0.8, tile=(1.0, 1.0)),
                  Material("gravel", tint=_colour(rng, 0.4, 0.8), contrast=0.3, tile=(0.8, 0.8))]
    for k in range(2):
        w, t, h = rng.uniform(0.8, 1.2), rng.uniform(0.02, 0.03), rng.uniform(1.4, 1.9)
        along_x = bool(rng.integers(2))
        half = (w / 2, t / 2) if along_x else (t / 2, w / 2)
        c = pl.sample(rng, half, h)
        if c is not None:
            b.add_box_on(c, 0.0, (2 * half[0], 2 * half[1], h), panel_mats[k])
    # coat stand: pole, cross feet, angled hooks
    c = pl.sample(rng, (0.3, 0.3), 1.8)
    if c is not None:
        b.add_post(c, 0.0, 1.8, 0.015, metal, 10)
        for a in np.arange(4) * np.pi / 2 + rng.uniform(0, np.pi / 2):
            d = np.array([np.cos(a), np.sin(a)])
            b.add_cylinder((*c, 0.02), (*(c + 0.28 * d), 0.02), 0.012, metal, 8)
            b.add_cylinder((*c, 1.6), (*(c + 0.14 * d), 1.72), 0.008, chrome, 8)
    # open wire shelf: four rods and thin boards
    spot = pl.against_wall(rng, 0.8, 0.3, 1.5)
    if spot is not None:
        cc, yaw = spot
        e_w, e_d = np.array([np.cos(yaw), np.sin(yaw)]), np.array([-np.sin(yaw), np.cos(yaw)])
        for a in (-1, 1):
            for d in (-1, 1):
                b.add_post(cc + a * 0.38 * e_w + d * 0.13 * e_d, 0.0, 1.5, 0.01, chrome, 8)
        for z in np.linspace(0.3, 1.48, 4):
            b.add_box_on(cc, z, (0.8, 0.3, 0.02), _wood(rng), yaw=yaw)
            if z < 1.4:
                _small_items(b, rng, cc, (0.3, 0.1) if abs(np.cos(yaw)) > 0.5 else (0.1, 0.3), z + 0.02, 0.15, 2, mats)
    for _ in range(3):
        _box_stack(b, pl, rng, mats, size=(0.2, 0.4), max_height=0.6, levels=2)
    return SceneLayout("thin", b.build(), path, default_frames=DEFAULT_FRAMES["thin"])
