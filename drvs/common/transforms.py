"""Rotations as tf writes them: 3x3 matrices <-> unit quaternions (x, y, z, w).

``tf.transformations`` is not packaged for Debian's Python 3, so this is the one
conversion DRVS needs, in numpy. Quaternions are in ROS order (x, y, z, w), as in
``geometry_msgs/Quaternion``, and returned with ``w >= 0`` (q and -q are the same
rotation; one sign makes results comparable).

>>> [round(float(c), 9) for c in quaternion_from_matrix([[1, 0, 0], [0, -1, 0], [0, 0, -1]])]
[1.0, 0.0, 0.0, 0.0]
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

ORTHONORMAL_TOLERANCE = 1e-6
"""Largest deviation of ``R @ R.T`` from the identity (and of ``det R`` from 1) accepted as a rotation."""


def quaternion_from_matrix(rotation: ArrayLike) -> np.ndarray:
    """The unit quaternion (x, y, z, w), ``w >= 0``, of a 3x3 rotation matrix.

    Shepperd's method: the largest of w, x, y, z is found from the diagonal first and
    divided by, so no branch loses precision (the rotation of 180 degrees about x of a
    camera looking straight down has w = 0).

    :raises ValueError: if ``rotation`` is not a 3x3 rotation matrix.
    """
    r = np.asarray(rotation, float)
    if r.shape != (3, 3) or not np.all(np.isfinite(r)):
        raise ValueError(f'rotation: expected a finite 3x3 matrix, got shape {r.shape}')
    if (
        np.max(np.abs(r @ r.T - np.eye(3))) > ORTHONORMAL_TOLERANCE
        or abs(np.linalg.det(r) - 1.0) > ORTHONORMAL_TOLERANCE
    ):
        raise ValueError('rotation: not a rotation matrix (R R^T = I and det R = 1 required)')
    trace = np.trace(r)
    candidates = (trace, r[0, 0], r[1, 1], r[2, 2])
    largest = int(np.argmax(candidates))
    if largest == 0:
        s = 2.0 * np.sqrt(1.0 + trace)  # s = 4 w
        q = ((r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, s / 4.0)
    elif largest == 1:
        s = 2.0 * np.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2])  # s = 4 x
        q = (s / 4.0, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s, (r[2, 1] - r[1, 2]) / s)
    elif largest == 2:
        s = 2.0 * np.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2])  # s = 4 y
        q = ((r[0, 1] + r[1, 0]) / s, s / 4.0, (r[1, 2] + r[2, 1]) / s, (r[0, 2] - r[2, 0]) / s)
    else:
        s = 2.0 * np.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1])  # s = 4 z
        q = ((r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, s / 4.0, (r[1, 0] - r[0, 1]) / s)
    unit = np.asarray(q, float)
    unit /= np.linalg.norm(unit)
    return (-unit if unit[3] < 0 else unit) + 0.0  # + 0.0: no -0.0 in messages


def matrix_from_quaternion(quaternion: ArrayLike) -> np.ndarray:
    """The 3x3 rotation matrix of a quaternion (x, y, z, w); it is normalised first.

    :raises ValueError: if ``quaternion`` is not 4 finite numbers of non-zero length.
    """
    q = np.asarray(quaternion, float)
    norm = float(np.linalg.norm(q)) if q.shape == (4,) else 0.0
    if not (np.isfinite(norm) and norm > 0):
        raise ValueError(f'quaternion: expected 4 finite numbers (x, y, z, w) not all 0, got {quaternion!r}')
    x, y, z, w = q / norm
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
