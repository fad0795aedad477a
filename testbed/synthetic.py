"""The paper's synthetic points-and-lines set-up (Guéziec et al. 1998, s. IV-B, Figs. 8-9).

Points uniform in the unit cube; lines from a center of perspective through them (a bundle
of about 20 degrees for the default center (-2, -2, -2)); the whole configuration turned by
a rotation of random axis and angle; then the points alone turned by ``rotation_deg`` about a
random axis and moved by a random vector of length ``translation_norm``. A fraction of the
points is then corrupted by zero-mean Gaussian noise. The truth is the transform
``points2lines`` that puts the (uncorrupted) points back on their lines.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from reglib.geometry import RigidTransform

__all__ = ["PointsLinesCase", "make_points_lines", "landmark_error"]


@dataclass(frozen=True)
class PointsLinesCase:
    """One synthetic instance with its truth.

    points : (N, 3) the moved (and partly corrupted) points, unit-cube units.
    origins, directions : (N, 3) the lines (unit directions).
    points2lines : the true transform (``points2lines.apply(clean points)`` lie on the lines).
    corrupted : (N,) bool, the points that received noise.
    landmarks : (L, 3) landmark points in the points' frame.
    """

    points: np.ndarray
    origins: np.ndarray
    directions: np.ndarray
    points2lines: RigidTransform
    corrupted: np.ndarray
    landmarks: np.ndarray


def _random_axis(rng):
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def make_points_lines(spec, rng=None, *, n_points=None, noise_std=None,
                      outlier_fraction=None) -> PointsLinesCase:
    """Draw one instance of the set-up described by ``spec`` (a ``SyntheticSpec``).

    ``n_points``, ``noise_std``, ``outlier_fraction`` override the spec's values.
    """
    rng = np.random.default_rng(rng)
    n = spec.n_points if n_points is None else int(n_points)
    std = spec.noise_std if noise_std is None else float(noise_std)
    frac = spec.outlier_fraction if outlier_fraction is None else float(outlier_fraction)
    p = rng.uniform(0.0, 1.0, size=(n, 3))
    c = np.asarray(spec.center_of_perspective, dtype=np.float64)
    # the whole configuration under a rotation of random axis and angle
    G = Rotation.random(random_state=rng)
    p_g = G.apply(p)
    c_g = G.apply(c)
    d = p_g - c_g
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    origins = np.broadcast_to(c_g, (n, 3)).copy()
    # the points alone: rotation of rotation_deg about a random axis, random translation
    move = RigidTransform.from_rotvec(
        np.radians(spec.rotation_deg) * _random_axis(rng),
        spec.translation_norm * _random_axis(rng),
    )
    moved = move.apply(p_g)
    k = int(round(frac * n))
    corrupted = np.zeros(n, dtype=bool)
    if k > 0 and std > 0:
        idx = rng.choice(n, k, replace=False)
        corrupted[idx] = True
        moved[idx] += rng.normal(0.0, std, size=(k, 3))
    return PointsLinesCase(
        points=moved,
        origins=origins,
        directions=d,
        points2lines=move.inverse(),
        corrupted=corrupted,
        landmarks=np.asarray(spec.landmarks, dtype=np.float64),
    )


def landmark_error(estimate: RigidTransform, truth: RigidTransform, landmarks) -> float:
    """The paper's error: the largest distance between landmarks under the two transforms."""
    lm = np.asarray(landmarks, dtype=np.float64)
    return float(np.max(np.linalg.norm(estimate.apply(lm) - truth.apply(lm), axis=1)))
