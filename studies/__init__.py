"""Studies: the judge. Each study is a module ``studies/<name>.py`` (dashes in the name become
underscores) that defines

- ``TITLE``: one line for ``testbed study --list``;
- ``DEFAULT_SCENE``: the scene name it uses when none is given;
- ``run(ctx: StudyContext) -> pandas.DataFrame``: the long-format results (columns ``trial``,
  ``metric``, ``value``, ``unit`` plus parameter columns). It may write figures into
  ``ctx.out`` and add report sections with ``ctx.report``.

:func:`run_study` resolves the scene and seed, runs the study, and writes ``results.csv``,
``report.md`` (with the resolved scene, seed and git commit) and the figures.
"""

from __future__ import annotations

import importlib
import os
import pkgutil
from pathlib import Path

__all__ = ["available_studies", "run_study"]


def _module_name(name: str) -> str:
    return "studies." + name.replace("-", "_")


def available_studies() -> dict[str, str]:
    """Study name -> title, for every module of ``studies`` that defines ``run`` and TITLE."""
    out = {}
    pkg_dir = Path(__file__).parent
    for info in pkgutil.iter_modules([str(pkg_dir)]):
        if info.name.startswith("_") or info.name in {"common", "main_job", "runner", "report"}:
            continue
        try:
            mod = importlib.import_module("studies." + info.name)
        except ImportError:
            continue
        if hasattr(mod, "run") and hasattr(mod, "TITLE"):
            out[info.name.replace("_", "-")] = mod.TITLE
    return dict(sorted(out.items()))


#: studies that cannot use parallel workers, and why
SERIAL_STUDIES = {"table1": "it times pose solves, and parallel workers would share the cores "
                            "it measures"}


def check_serial(name: str, workers: int = 1, scheduler=None) -> None:
    """ValueError when a study of :data:`SERIAL_STUDIES` is given workers or a scheduler
    (``testbed study`` asks before it connects to the scheduler: a review, h97, saw the
    connection fail first)."""
    if name in SERIAL_STUDIES and (workers != 1 or scheduler is not None):
        raise ValueError(f"testbed study {name}: --workers and --scheduler are refused: "
                         f"{SERIAL_STUDIES[name]}")


def study_owner(name: str, scene, seed, quick: bool) -> str:
    """Who a study folder's trials belong to: the study, its scene file (the absolute path,
    however it was typed), its seed and ``--quick``. Another scene or seed in the same
    folder replaced the results and mixed both runs' trials in the database (a review);
    ``testbed score`` names its dataset likewise. The scene's contents are not part of it:
    a scene edited and run again into its folder runs the trials whose inputs changed (their
    keys hold the contents), as before."""
    from testbed.scene import find_scene, load_scene

    path = find_scene(scene)
    if seed is None:
        seed = load_scene(path).scene.seed
    quick_note = ", quick" if quick else ""
    return f"{name} of {os.path.abspath(path)}, seed {int(seed)}{quick_note}"


#: studies that move the scene's views (capture-range re-aims them at each random femur):
#: the warnings about their aim do not apply to their cases, and are left out; those of the
#: regions and the CT's reach stand (a held-out review: a CT of the proximal end only gave
#: capture ranges of 0 mm for every method without a word)
REAIMED_VIEWS = ("capture-range",)


def run_study(name: str, out: Path, *, scene=None, seed=None, quick=False, workers=1,
              scheduler=None, retries: int = 2, progress: bool = True,
              retry_failed: bool = False) -> Path:
    """Run study ``name`` into folder ``out``; returns ``out``.

    ``workers``: processes for the trials; ``scheduler``: a Dask scheduler address (or
    Client / cluster) to run them on instead; ``retries``: how many more times a trial whose
    worker was lost is run; ``progress``: a bar of the trials on stderr. Rerunning into the
    same ``out`` resumes (the trials stored as failed run again with ``retry_failed``).
    Raises ``ValueError`` before any work for an unknown study, a
    scene of another kind than the study's default scene (e.g. an operating room for
    ``fig9``), a scene the study's module refuses (its ``check_scene``), or workers asked of
    a serial study.
    """
    from studies.common import (
        check_out_folder,
        finish_study,
        report_scene_warnings,
        start_study,
    )
    from testbed.scene import find_scene, load_scene

    known = available_studies()
    if name not in known:
        raise ValueError(f"testbed study: unknown study {name!r}; known: {', '.join(known)}")
    mod = importlib.import_module(_module_name(name))
    check_serial(name, workers, scheduler)
    if scene is not None:
        want = load_scene(find_scene(mod.DEFAULT_SCENE)).scene.kind
        path = find_scene(scene)
        got = load_scene(path).scene.kind
        if got != want:
            raise ValueError(f"{path}: [scene] kind = {got!r}, but study {name} needs a "
                             f"scene of kind {want!r} (e.g. {mod.DEFAULT_SCENE})")
    owner = study_owner(name, scene or mod.DEFAULT_SCENE, seed, quick)
    check_out_folder(out, name, study=owner)
    ctx = start_study(name, out, scene=scene or mod.DEFAULT_SCENE, seed=seed, quick=quick,
                      workers=workers, scheduler=scheduler)
    ctx.owner = owner
    ctx.retries = int(retries)
    ctx.progress = bool(progress)
    ctx.retry_failed = bool(retry_failed)
    # a scene the study cannot use is refused before any work (its module's check_scene)
    if hasattr(mod, "check_scene"):
        mod.check_scene(ctx.scene, ctx.scene_path)
    if ctx.scene.scene.kind == "operating_room":
        from studies.end_to_end import scene_warnings

        reaimed = name in REAIMED_VIEWS
        report_scene_warnings(
            ctx, scene_warnings(ctx.scene, int(ctx.seed), aim=not reaimed),
            "this scene at the study's seed"
            + (" (of the scene's own femur, where this study draws a random femur per "
               "case, and without the aim of its views, which it re-aims at each)"
               if reaimed else ""))
    df = mod.run(ctx)
    finish_study(ctx, df)
    return out
