"""Scoring against the truth: pin errors, mTRE, and the perturbed starts (one copy of each).

Frames and units: ``ct2robot`` transforms (:class:`reglib.geometry.RigidTransform`), pins
and targets in ct mm, errors in mm.
"""

from __future__ import annotations

import numpy as np

from reglib.geometry import RigidTransform
from testbed.phantom import PIN_NAMES
from testbed.seeds import keyed_seed

__all__ = [
    "JUDGE_STREAM",
    "PIN_NAMES",
    "as_transform",
    "judge_seed",
    "mtre",
    "perturbed_start",
    "pin_reference",
    "pin_errors",
    "run_start",
    "start_at_mtre",
]

#: child of a case's SeedSequence that the judge uses for its starts (far from the
#: simulator's streams, testbed.simulate.SEED_STREAMS)
JUDGE_STREAM = 1000


def as_transform(pose) -> RigidTransform:
    """A RigidTransform from itself or a (4, 4) matrix."""
    if isinstance(pose, RigidTransform):
        return pose
    m = np.asarray(pose, dtype=np.float64)
    if m.shape != (4, 4):
        raise ValueError(f"expected a RigidTransform or a (4, 4) matrix, got shape {m.shape}")
    return RigidTransform(m[:3, :3], m[:3, 3])


def pin_errors(estimate, truth, pins_ct: dict) -> dict[str, float]:
    """Error (mm) at each pin: distance between its estimated and true robot positions."""
    est, tru = as_transform(estimate), as_transform(truth)
    return {k: float(np.linalg.norm(est.apply(np.asarray(pins_ct[k], float))
                                    - tru.apply(np.asarray(pins_ct[k], float))))
            for k in PIN_NAMES if k in pins_ct}


def mtre(pose, truth, targets_ct) -> float:
    """Mean distance (mm) between the targets (N, 3) ct mm mapped by ``pose`` and ``truth``."""
    t = np.asarray(targets_ct, dtype=np.float64).reshape(-1, 3)
    return float(np.mean(np.linalg.norm(as_transform(pose).apply(t)
                                        - as_transform(truth).apply(t), axis=1)))


def judge_seed(case_ss: np.random.SeedSequence, *salt: int) -> np.random.SeedSequence:
    """The judge's own SeedSequence for a case (its starts), optionally salted further."""
    return keyed_seed(case_ss, JUDGE_STREAM, *salt)


def perturbed_start(ct2robot, pins_ct: dict, angle_deg: float, rng, *,
                    about: str | None = None) -> RigidTransform:
    """``ct2robot`` turned by ``angle_deg`` about a random axis through the pins' centroid
    (or through the pin ``about``), so that point stays where the truth puts it (the
    paper's Table II starts)."""
    rng = np.random.default_rng(rng)
    truth = as_transform(ct2robot)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    centre_ct = (np.asarray(pins_ct[about], float) if about
                 else np.mean([pins_ct[k] for k in PIN_NAMES], axis=0))
    centre = truth.apply(centre_ct)
    rot = RigidTransform.from_rotvec(np.radians(angle_deg) * axis)
    return RigidTransform(rot.R, centre - rot.R @ centre) @ truth


#: the judge's seed salt of the pin-based registration that a located pin's start is made
#: from (the salt of the table2 and experiment1 studies' reference)
REFERENCE_SALT = 3


def run_start(truth, scene, case_ss: np.random.SeedSequence) -> RigidTransform:
    """The start of ``testbed run`` (and of ``testbed score``) for a case: the true pose
    turned by the scene's ``[registration] start_rotation_deg`` about a random axis through
    the pins' centroid, drawn from :func:`judge_seed`. With a ``fixed_pin``, whose robot
    position the start must already hold (the paper's experiment 1), the turn is of the
    pin-based registration (:func:`pin_reference`, as the paper started) about that pin:
    the located pin keeps the error of its location in CT and by the robot, and is not
    handed to the method exactly.

    ``truth``: a ``testbed.dataset.Truth`` (``transforms['ct2robot']``, ``points['pins_ct']``).
    """
    reg = scene.registration
    pose = truth.transforms["ct2robot"]
    if reg.fixed_pin:
        pose = case_reference(truth, case_ss)
    return perturbed_start(pose, truth.points["pins_ct"], reg.start_rotation_deg,
                           np.random.default_rng(judge_seed(case_ss)),
                           about=reg.fixed_pin or None)


def start_at_mtre(truth, targets_ct, target_mm: float, rng, *,
                  tol_mm: float = 1e-3) -> RigidTransform:
    """A start ``ct2robot`` whose mTRE at ``targets_ct`` (N, 3) ct mm is ``target_mm``.

    A random direction in the 6-D space (rotation vector about the targets' centroid, in rad
    times their mean distance to it, i.e. mm at the targets; translation in mm), uniform on
    the sphere, is scaled by bisection until the mTRE matches within ``tol_mm``.
    """
    if not np.isfinite(target_mm) or target_mm < 0:
        raise ValueError(f"target_mm: expected a finite mTRE >= 0 mm, got {target_mm}")
    rng = np.random.default_rng(rng)
    truth = as_transform(truth)
    t = np.asarray(targets_ct, dtype=np.float64)
    if t.ndim != 2 or t.shape[1] != 3 or len(t) < 1:
        raise ValueError(f"targets_ct: expected an (N, 3) array of points, got {t.shape}")
    centre = truth.apply(t.mean(axis=0))
    radius = max(float(np.mean(np.linalg.norm(t - t.mean(axis=0), axis=1))), 1.0)
    u = rng.normal(size=6)
    u /= np.linalg.norm(u)

    def pose(s):
        rot = RigidTransform.from_rotvec(s * u[:3] / radius)
        return RigidTransform(rot.R, centre - rot.R @ centre + s * u[3:]) @ truth

    if target_mm == 0:
        return truth
    lo, hi = 0.0, target_mm
    while mtre(pose(hi), truth, t) < target_mm:
        hi *= 2.0
        if hi > 1e4:
            raise ValueError(f"target_mm = {target_mm}: cannot reach that mTRE")
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        if mtre(pose(mid), truth, t) < target_mm:
            lo = mid
        else:
            hi = mid
        if hi - lo < 1e-9 or abs(mtre(pose(mid), truth, t) - target_mm) < tol_mm:
            break
    return pose(0.5 * (lo + hi))


#: localisation error of a pin centre in the CT (mm, standard deviation per axis): about a
#: quarter of the 1 mm slice spacing and the 0.8 mm pixel around the pins (docs/error-model.md)
REFERENCE_CT_SIGMA_MM = 0.25
#: the robot's error when it touches a pin with its probe (mm, per axis): its absolute
#: accuracy, 0.1-0.6 mm for surgical arms (docs/error-model.md)
REFERENCE_ROBOT_SIGMA_MM = 0.25


def case_reference(truth, case_ss: np.random.SeedSequence) -> RigidTransform:
    """The case's pin-based reference registration: :func:`pin_reference` drawn from the
    judge's stream at :data:`REFERENCE_SALT`, the same in ``testbed run``, ``score`` and the
    studies."""
    return pin_reference(truth, judge_seed(case_ss, REFERENCE_SALT))


def pin_reference(truth, rng, *, ct_sigma_mm: float = REFERENCE_CT_SIGMA_MM,
                  robot_sigma_mm: float = REFERENCE_ROBOT_SIGMA_MM) -> RigidTransform:
    """The paper's reference pose: a pin-based registration with its own error.

    The pins are located in the CT, each with a Gaussian error (``ct_sigma_mm`` per axis),
    and touched by the robot: where the case's truth holds the positions its own robot
    reported (``points['pins_robot_digitized']``, :meth:`testbed.robot.Robot.digitize`:
    the robot's absolute error at each pin, shared in part with its sweeps), those; else
    (a pin the robot could not reach, a dataset written before) a Gaussian error
    (``robot_sigma_mm`` per axis). The rigid transform that best maps the CT positions onto
    the robot's (least squares, Kabsch) is the reference ``ct2robot``. The paper measured
    its Table II against such a reference; reporting errors against it beside the errors
    against the truth compares like with like.
    """
    rng = np.random.default_rng(rng)
    names = [k for k in PIN_NAMES if k in truth.points["pins_ct"]]
    p_ct = np.array([truth.points["pins_ct"][k] for k in names], dtype=np.float64)
    p_robot = as_transform(truth.transforms["ct2robot"]).apply(p_ct)
    a = p_ct + rng.normal(0.0, ct_sigma_mm, p_ct.shape)
    b = p_robot + rng.normal(0.0, robot_sigma_mm, p_robot.shape)
    touched = truth.points.get("pins_robot_digitized")
    touched = touched if isinstance(touched, dict) else {}    # named points, or none
    for i, k in enumerate(names):    # the Gaussian drawn all the same: one stream either way
        p = np.asarray(touched.get(k, np.nan), dtype=np.float64)
        if p.shape == (3,) and np.all(np.isfinite(p)):
            b[i] = p
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    u, _, vt = np.linalg.svd((a - ca).T @ (b - cb))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    R = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return RigidTransform(R, cb - R @ ca)
