"""Axis conventions. Internally everything is camera-to-world in OpenCV axes (x right, y down, z forward).

OpenGL / NeRF axes (x right, y up, z backward) differ by negating the camera y and z axes, i.e. the 2nd and 3rd
columns of the rotation part of c2w. The map is its own inverse.
"""

from __future__ import annotations

import numpy as np

_FLIP = np.diag([1.0, -1.0, -1.0, 1.0])


def opengl_to_opencv(c2w: np.ndarray) -> np.ndarray:
    """(..., 4, 4) OpenGL-axes camera-to-world -> OpenCV-axes camera-to-world."""
    return np.asarray(c2w, dtype=np.float64) @ _FLIP


opencv_to_opengl = opengl_to_opencv
