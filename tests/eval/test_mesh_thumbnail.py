"""The mesh picture of a run directory (mesh.png): the rasteriser on analytic triangles, the view, bad input."""

from __future__ import annotations

import numpy as np
import pytest

from inrslam.errors import DataError
from inrslam.eval.mesh_thumbnail import AMBIENT, BACKGROUND, mesh_thumbnail, rasterise, view_basis

RED, GREEN, BLUE = np.eye(3)


def one_triangle(colors=None, depth=(1.0, 1.0, 1.0)):
    """Right triangle with legs of 8 px from the top-left corner of a 10 x 10 picture, unshaded."""
    xy = np.array([[0.0, 0.0], [8.0, 0.0], [0.0, 8.0]])
    cols = np.tile([0.2, 0.4, 0.6], (3, 1)) if colors is None else colors
    return rasterise(xy, np.asarray(depth), np.array([[0, 1, 2]]), cols, np.ones(1), (10, 10))


def test_a_triangle_covers_exactly_the_pixel_centres_inside_it():
    rgb, face = one_triangle()
    col, row = np.meshgrid(np.arange(10), np.arange(10))
    inside = (col + 0.5) + (row + 0.5) <= 8.0  # x + y <= 8 at the pixel centre
    assert inside.sum() == 36
    assert np.array_equal(face >= 0, inside)
    assert np.allclose(rgb[inside], [0.2, 0.4, 0.6]) and not rgb[~inside].any()


def test_vertex_colours_are_interpolated_across_the_triangle():
    rgb, face = one_triangle(colors=np.stack([RED, GREEN, BLUE]))
    # pixel (0, 0) has its centre at (0.5, 0.5): barycentric weights 7/8, 1/16, 1/16
    assert np.allclose(rgb[0, 0], [7 / 8, 1 / 16, 1 / 16])
    assert np.allclose(rgb[face >= 0].sum(axis=1), 1.0)  # weights sum to one everywhere


def test_the_nearer_triangle_wins_whatever_the_order():
    big = [[0.0, 0.0], [20.0, 0.0], [0.0, 20.0]]  # covers the whole upper-left half and more
    small = [[1.0, 1.0], [5.0, 1.0], [1.0, 5.0]]  # inside it
    xy = np.array(big + small)
    _, alone = rasterise(np.array(small), np.ones(3), np.array([[0, 1, 2]]), np.ones((3, 3)), np.ones(1), (10, 10))
    small_area = alone >= 0
    assert small_area.sum() == 10  # pixel centres with x, y >= 1 and x + y <= 6
    colors = np.stack([RED] * 3 + [BLUE] * 3)
    for z_small, small_seen in ((0.5, True), (2.0, False)):  # the big one is at 1 m
        depth = np.array([1.0] * 3 + [z_small] * 3)
        for order in ([0, 1], [1, 0]):
            faces = np.array([[0, 1, 2], [3, 4, 5]])[order]
            small_index = order.index(1)
            rgb, face = rasterise(xy, depth, faces, colors, np.ones(2), (10, 10))
            assert ((face == small_index) == (small_area & small_seen)).all()
            assert np.allclose(rgb[small_area], BLUE if small_seen else RED)


def test_two_triangles_sharing_an_edge_leave_no_crack():
    xy = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0], [10.0, 10.0]])
    faces = np.array([[0, 1, 2], [3, 2, 1]])  # a 10 x 10 square cut along its diagonal
    rgb, face = rasterise(xy, np.ones(4), faces, np.ones((4, 3)), np.ones(2), (10, 10))
    assert (face >= 0).all()
    assert (face[np.arange(10), 9 - np.arange(10)] == 0).all()  # centres on the shared edge: a tie, lower index


def test_shade_scales_the_colour_and_empty_input_draws_nothing():
    xy = np.array([[0.0, 0.0], [8.0, 0.0], [0.0, 8.0]])
    rgb, face = rasterise(xy, np.ones(3), np.array([[0, 1, 2]]), np.ones((3, 3)), np.array([0.5]), (10, 10))
    assert np.allclose(rgb[face >= 0], 0.5)
    rgb, face = rasterise(xy, np.ones(3), np.zeros((0, 3), int), np.ones((3, 3)), np.zeros(0), (10, 10))
    assert (face == -1).all() and not rgb.any()


def square(flip: bool = False):
    """1 m square in the plane z = 0, normal +z (counter-clockwise seen from above), or -z when `flip`."""
    v = np.array([[-0.5, -0.5, 0.0], [0.5, -0.5, 0.0], [0.5, 0.5, 0.0], [-0.5, 0.5, 0.0]])
    f = np.array([[0, 1, 2], [0, 2, 3]])
    return v, (f[:, ::-1] if flip else f)


def test_thumbnail_shows_front_faces_fitted_and_shaded():
    v, f = square()
    color = np.array([200, 100, 50], np.uint8)
    img = mesh_thumbnail(v, f, np.tile(color, (4, 1)), up=(0, 0, 1), size=(64, 48), elevation_deg=90.0)
    assert img.shape == (48, 64, 3) and img.dtype == np.uint8
    basis = view_basis(np.array([0.0, 0.0, 1.0]), 90.0)
    light = -basis[2] + 0.35 * basis[0] + 0.35 * basis[1]  # the face's normal is the view direction -basis[2]
    shade = AMBIENT + (1 - AMBIENT) / np.linalg.norm(light)
    assert np.allclose(img[24, 32], np.round(color * shade), atol=1)
    drawn = (img != BACKGROUND).any(axis=2)
    # seen from above the square is a diamond (the view's right is the floor's diagonal) fitted with a 4 % margin
    rows, cols = np.nonzero(drawn)
    assert rows.min() >= 1 and rows.max() <= 46 and rows.max() - rows.min() >= 40
    assert drawn[24, 1:63].sum() >= 40 and not drawn[0, 0] and not drawn[47, 63]
    # its back (normal pointing away from the viewer) is culled: nothing is drawn
    assert (mesh_thumbnail(*square(flip=True), up=(0, 0, 1), size=(64, 48), elevation_deg=90.0) == BACKGROUND).all()


def test_view_basis_is_orthonormal_and_looks_down_from_60_degrees():
    for up in ([0, 0, 1], [0, -1, 0], [1, 0, 0]):
        b = view_basis(np.array(up, dtype=float))
        assert np.allclose(b @ b.T, np.eye(3), atol=1e-12)
        assert abs(b[0] @ up) < 1e-12  # the picture's horizontal is level
        assert np.isclose(-b[2] @ up, np.sin(np.radians(60.0)))  # the viewer is 60 degrees above the horizon


@pytest.mark.parametrize("args, match", [
    ((np.zeros((4, 2)), np.array([[0, 1, 2]])), r"vertices must be \(V, 3\)"),
    ((np.zeros((4, 3)), np.array([[0, 1, 4]])), "face indices must lie in 0..3"),
    ((np.zeros((4, 3)), np.array([[0.0, 1.0, 2.0]])), "integer vertex indices"),
    ((np.zeros((4, 3)), np.array([[0, 1, 2]]), np.zeros((3, 3))), r"colours must be \(4, 3\)"),
])
def test_bad_input_is_a_one_line_error(args, match):
    with pytest.raises(DataError, match=match) as e:
        mesh_thumbnail(*args)
    assert "\n" not in str(e.value)
    with pytest.raises(DataError, match="up direction"):
        mesh_thumbnail(*square(), up=(0, 0, 0))


def test_a_200k_triangle_mesh_is_drawn_whole(make_plane):
    # its time is measured by benchmarks/bench_thumbnail.py (tests never time anything)
    plane = make_plane(4.0, 317)  # 201,000 triangles
    assert len(plane.faces) > 200_000
    img = mesh_thumbnail(plane.vertices, plane.faces, up=(0, 0, 1))
    assert (img != BACKGROUND).any(axis=2).mean() > 0.3  # the plane fills much of the picture, without holes
