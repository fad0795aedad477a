"""reglib: anatomy-based registration of CT to calibrated X-ray views (Gueziec et al. 1998).

Arrays and small dataclasses in, the same out; no simulator, no I/O. The one call::

    import reglib
    est = reglib.estimate(observation, initial_ct2robot)   # -> reglib.Estimate
    est.ct2robot, est.accepted, est.quality, est.message

The stages are public too: :func:`reglib.pipeline.calibrate_view`,
:func:`reglib.pipeline.ct_surfaces`, :func:`reglib.pipeline.xray_contours`,
:func:`reglib.register.register` and :func:`reglib.pose.solve_pose`.

The names below are loaded on first use (PEP 562), so that ``import reglib.geometry`` (all
the simulator uses of reglib) loads nothing else.
"""

from importlib import import_module

__all__ = [
    "Estimate",
    "EstimateOptions",
    "RigidTransform",
    "Stages",
    "calibrate_view",
    "ct_surfaces",
    "estimate",
    "prepare",
]

_WHERE = {"RigidTransform": "reglib.geometry", **{n: "reglib.pipeline" for n in __all__
                                                   if n != "RigidTransform"}}


def __getattr__(name):
    if name in _WHERE:
        value = getattr(import_module(_WHERE[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'reglib' has no attribute {name!r}")


def __dir__():
    return sorted(list(globals()) + __all__)
