"""Poses and SE(2) transforms in metres and radians.

A transform named ``b_from_a`` maps a point given in frame ``a`` into frame ``b``:
``p_b = R(theta) p_a + t``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

# The farthest (metres, in x or in y) a map's origin or a pose may lie from its frame's
# origin: beyond any building, even in UTM coordinates (northings up to 1e7 m). Past it the
# transforms lose every centimetre to rounding and arrays sized by coordinates overflow.
MAX_COORDINATE_M = 1e7


def wrap_angle(angle_rad: float) -> float:
    """Wrap an angle to [-pi, pi)."""
    return (angle_rad + math.pi) % (2.0 * math.pi) - math.pi


def yaw_from_quaternion(x: float, y: float, z: float, w: float) -> float:
    """Yaw (rotation about z, radians) of a ROS quaternion ``(x, y, z, w)``.

    Raises ``ValueError`` when the quaternion has zero length.
    """
    norm = math.sqrt(x * x + y * y + z * z + w * w)
    if not norm > 1e-9 or not math.isfinite(norm):
        raise ValueError(f"quaternion must have a non-zero finite length, got {(x, y, z, w)}")
    x, y, z, w = x / norm, y / norm, z / norm, w / norm
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


@dataclass(frozen=True)
class Pose2D:
    """A planar pose: position in metres, heading in radians."""

    x: float
    y: float
    yaw: float


@dataclass(frozen=True)
class Transform2D:
    """A rigid transform ``p_target = R(theta) p_source + (tx, ty)``."""

    theta: float
    tx: float
    ty: float

    @staticmethod
    def identity() -> Transform2D:
        return Transform2D(0.0, 0.0, 0.0)

    @staticmethod
    def from_poses(pose_target: Pose2D, pose_source: Pose2D) -> Transform2D:
        """The transform that maps ``pose_source`` onto ``pose_target`` (the same robot pose seen in
        two frames): ``theta = yaw_t - yaw_s``, ``t = xy_t - R(theta) xy_s``."""
        theta = wrap_angle(pose_target.yaw - pose_source.yaw)
        c, s = math.cos(theta), math.sin(theta)
        tx = pose_target.x - (c * pose_source.x - s * pose_source.y)
        ty = pose_target.y - (s * pose_source.x + c * pose_source.y)
        return Transform2D(theta, tx, ty)

    def matrix(self) -> NDArray[np.float64]:
        """The 3x3 homogeneous matrix."""
        c, s = math.cos(self.theta), math.sin(self.theta)
        return np.array([[c, -s, self.tx], [s, c, self.ty], [0.0, 0.0, 1.0]])

    @staticmethod
    def from_matrix(m: ArrayLike) -> Transform2D:
        a = np.asarray(m, dtype=float)
        return Transform2D(math.atan2(a[1, 0], a[0, 0]), float(a[0, 2]), float(a[1, 2]))

    def apply(self, points_xy: ArrayLike) -> NDArray[np.float64]:
        """Map points of shape (N, 2) (or one point of shape (2,)) from source to target."""
        p = np.asarray(points_xy, dtype=float)
        c, s = math.cos(self.theta), math.sin(self.theta)
        # Elementwise, not a matrix product: numpy hands those to a BLAS whose threads spin
        # on every core, which costs a daemon worker beside another one a third of its speed.
        out = np.empty(p.shape)
        x, y = p[..., 0], p[..., 1]
        out[..., 0] = c * x - s * y + self.tx
        out[..., 1] = s * x + c * y + self.ty
        return out

    def compose(self, other: Transform2D) -> Transform2D:
        """``self o other``: first ``other``, then ``self``."""
        return Transform2D.from_matrix(self.matrix() @ other.matrix())

    def inverse(self) -> Transform2D:
        return Transform2D.from_matrix(np.linalg.inv(self.matrix()))


def fit_rigid(src: ArrayLike, dst: ArrayLike) -> Transform2D:
    """The rigid transform that maps points ``src`` (N, 2) closest to ``dst`` (N, 2), in the
    least-squares sense (2-D Kabsch, no reflection). Raises ``ValueError`` on no points."""
    a = np.asarray(src, dtype=float).reshape(-1, 2)
    b = np.asarray(dst, dtype=float).reshape(-1, 2)
    if len(a) == 0 or len(a) != len(b):
        raise ValueError(f"need as many src as dst points, at least one: {len(a)} and {len(b)}")
    ca, cb = a.mean(0), b.mean(0)
    u, v = a - ca, b - cb
    theta = math.atan2(float(np.sum(u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0])), float(np.sum(u * v)))
    c, s = math.cos(theta), math.sin(theta)
    return Transform2D(
        theta, float(cb[0] - (c * ca[0] - s * ca[1])), float(cb[1] - (s * ca[0] + c * ca[1]))
    )
