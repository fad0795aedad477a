"""``testbed score``: score any registration method on a generated dataset.

A *method* is a function ``method(observation, initial) -> ct2robot`` that takes a case's
:class:`testbed.dataset.Observation` (what a clinic has; see ``docs/dataset-format.md``) and
the start pose as a (4, 4) ``ct2robot`` array (mm), and returns its estimate as a (4, 4)
array (or a :class:`reglib.geometry.RigidTransform`). It is named on the command line as
``pkg.module:function`` (importable from the current folder or the Python path); the default
is reglib's one call, :func:`reglib.estimate`, with the options of the dataset's scene.

Every case of the dataset is one trial on the study runner (resumable, failed cases as rows,
``--workers``): the case is loaded (checksums verified), the start drawn exactly as
``testbed run`` draws it for that scene and seed (:func:`studies.scoring.run_start`), the
method called, and its result scored at the pins. A method that raises, or returns something
that is not a finite rigid (4, 4) transform, gives a failed trial with the reason.

Output as for the studies: ``OUT/results.csv`` (``trial, metric, value, unit`` + ``case``,
``pin``: ``pin_error`` mm per pin, ``mtre`` mm, ``start_mtre`` mm, ``time`` s (the
method's wall time; a worker's first case includes its start-up), and for reglib's method
``accepted`` (with the verdict's ``reason`` when refused), ``converged`` and per view
``view_used`` (``view``, ``reason``: why the method left it out)) and ``OUT/report.md``.
"""

from __future__ import annotations

import dataclasses
import importlib
import inspect
import json
import sys
import time
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import pandas as pd

__all__ = ["DEFAULT_METHOD", "CaseInputs", "case_inputs", "load_method", "score_case",
           "score_dataset"]

DEFAULT_METHOD = "reglib"


def load_method(spec: str):
    """The function named ``pkg.module:function`` (``ValueError`` with a clear message when it
    cannot be imported or is not callable)."""
    if spec == DEFAULT_METHOD:
        return None
    if not isinstance(spec, str) or spec.count(":") != 1 or not all(spec.split(":")):
        raise ValueError(f"--method {spec!r}: expected pkg.module:function")
    mod_name, fn_name = spec.split(":")
    import sys

    if "" not in sys.path and str(Path.cwd()) not in sys.path:
        sys.path.insert(0, str(Path.cwd()))
    try:
        mod = importlib.import_module(mod_name)
    except (Exception, SystemExit) as exc:  # noqa: BLE001 - any failure of the user's module
        raise ValueError(f"--method {spec!r}: cannot import module {mod_name!r} "
                         f"({type(exc).__name__}: {exc})") from None
    fn = getattr(mod, fn_name, None)
    if not callable(fn):
        raise ValueError(f"--method {spec!r}: module {mod_name!r} has no function {fn_name!r}")
    try:
        inspect.signature(fn).bind(None, None)
    except TypeError:
        raise ValueError(f"--method {spec!r}: {fn_name}{inspect.signature(fn)} cannot be "
                         "called as method(observation, initial)") from None
    except ValueError:
        pass        # no signature to read (a builtin): called as it is
    return fn


def _as_pose(value, spec: str):
    """The pose a method returned, as :func:`reglib.geometry.as_rigid_transform` reads it,
    its refusals naming the method."""
    from reglib.geometry import as_rigid_transform

    return as_rigid_transform(value, f"method {spec} returned")


#: scene fields that a dataset's stored scene may hold from an older testbed and that this
#: one no longer has (they never had an effect): left out when a stored scene is read
REMOVED_FIELDS = (("robot", "sweep", "park_distance_mm"),)


def parse_stored_scene(data, *, source: str):
    """The scene a dataset's case stored (``meta.truth.scene``), read as
    :func:`testbed.scene.parse_scene` reads a file, less :data:`REMOVED_FIELDS` (a case
    written before a field was removed is still scored; a scene file that names one is
    refused, as any unknown key)."""
    import copy

    from testbed.scene import parse_scene

    if isinstance(data, dict):
        data = copy.deepcopy(data)
        for path in REMOVED_FIELDS:
            node = data
            for key in path[:-1]:
                node = node.get(key) if isinstance(node, dict) else None
            if isinstance(node, dict):
                node.pop(path[-1], None)
    return parse_scene(data, source=source)


def _check_truth(truth, case_dir) -> None:
    """ValueError naming the case and the entry when the truth the score needs is missing or
    not finite: ``transforms/ct2robot`` and the three pins of ``points/pins_ct`` (a review:
    a case whose truth lost a pin gave a bare KeyError, one with a NaN pin a message about
    a RigidTransform)."""
    from testbed.phantom import PIN_NAMES

    if "ct2robot" not in truth.transforms:
        raise ValueError(f"{case_dir}: the truth lacks transforms/ct2robot")
    pins = truth.points.get("pins_ct")
    if pins is None:
        raise ValueError(f"{case_dir}: the truth lacks points/pins_ct")
    if not isinstance(pins, dict):
        raise ValueError(f"{case_dir}: the truth's points/pins_ct must be a table of named "
                         f"pins (name -> 3 numbers, mm), got {type(pins).__name__} "
                         f"{np.shape(pins)}")
    for name in PIN_NAMES:
        if name not in pins:
            raise ValueError(f"{case_dir}: the truth's points/pins_ct lacks the pin {name!r} "
                             f"(it holds {sorted(pins)})")
        p = np.asarray(pins[name], dtype=np.float64)
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise ValueError(f"{case_dir}: the truth's pin {name!r} (points/pins_ct) must be "
                             f"3 finite numbers (mm), got {pins[name]!r}")


class CaseInputs(NamedTuple):
    """What ``testbed score`` gives a method for one case, and what it scores against."""

    observation: Any     #: testbed.dataset.Observation: what the method may see
    truth: Any           #: testbed.dataset.Truth: what it is scored against
    scene: Any           #: testbed.scene.Scene: the case's resolved scene (truth)
    start: Any           #: reglib.geometry.RigidTransform: the start ct2robot, mm
    options: Any         #: reglib.EstimateOptions: reglib's options for the scene


def case_inputs(case_dir) -> CaseInputs:
    """The inputs ``testbed score`` uses for the case in ``case_dir``: the loaded case, its
    stored scene, the start pose drawn as ``testbed run`` draws it
    (:func:`studies.scoring.run_start`) and ``reglib.estimate``'s options for the scene
    (its ``[registration]`` section, and with a ``fixed_pin`` the located pin, as
    ``testbed run`` gives it). ``reglib.estimate(c.observation, c.start,
    options=c.options)`` is the default method's score of the case, to the last bit when
    :func:`studies.numerics.apply` ran before numpy was imported (the ``testbed`` command
    does). ValueError naming the case when its truth or meta cannot be read."""
    from studies.end_to_end import estimate_options, with_fixed_pin
    from studies.scoring import run_start
    from testbed.dataset import load

    obs, truth = load(case_dir)
    _check_truth(truth, case_dir)
    tmeta = truth.meta.get("truth", truth.meta)
    try:
        scene = parse_stored_scene(tmeta["scene"], source=f"{case_dir}/case.json meta.truth.scene")
        seed = tmeta["seed"]
        case_ss = np.random.SeedSequence(int(seed["entropy"]),
                                         spawn_key=tuple(int(k) for k in seed["spawn_key"]))
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"{case_dir}/case.json: meta lacks the case's scene or seed ({exc}); "
                         "was it written by testbed generate?") from None
    start = run_start(truth, scene, case_ss)
    options = estimate_options(scene)
    if scene.registration.fixed_pin:   # the located pin, as testbed run gives it
        options = with_fixed_pin(options, truth.points["pins_ct"], scene.registration.fixed_pin)
    return CaseInputs(obs, truth, scene, start, options)


def score_case(case_dir, method: str = DEFAULT_METHOD) -> list[dict]:
    """Rows of one case (see the module docstring)."""
    import reglib
    from studies.end_to_end import view_used_row
    from studies.scoring import pin_errors

    obs, truth, _, start, options = case_inputs(case_dir)
    fn = load_method(method)
    rows = []
    t0 = time.perf_counter()
    if fn is None:
        est = reglib.estimate(obs, start, options=options)
        pose = est.ct2robot
        # the verdict's reason and the views left out, with the method's words (a held-out
        # review: a case refused for its field-of-view mask read "accepted: no", no cause)
        rows += [{"metric": "accepted", "value": float(est.accepted), "unit": "",
                  "reason": "" if est.accepted else str(est.message or "not accepted")},
                 {"metric": "converged", "value": float(est.converged), "unit": ""}]
        rows += [view_used_row(est.stages, v)
                 for v in (est.stages.calibrations if est.stages is not None else ())]
    else:
        pose = _as_pose(fn(obs, start.as_matrix()), method)
    dt = time.perf_counter() - t0
    truth_pose, pins = truth.transforms["ct2robot"], truth.points["pins_ct"]
    errs = pin_errors(pose, truth_pose, pins)
    start_errs = pin_errors(start, truth_pose, pins)
    rows += [{"metric": "pin_error", "value": e, "unit": "mm", "pin": p} for p, e in errs.items()]
    rows += [{"metric": "mtre", "value": float(np.mean(list(errs.values()))), "unit": "mm"},
             {"metric": "start_mtre", "value": float(np.mean(list(start_errs.values()))),
              "unit": "mm"},
             {"metric": "time", "value": dt, "unit": "s"}]
    return rows


#: at most this many refused cases are listed with their verdict's reason in the report
MAX_REFUSALS_LISTED = 20


def refusals_markdown(df: pd.DataFrame) -> str:
    """The report's list of the cases whose verdict refused the pose, each with the
    verdict's ``reason`` on one line (the first :data:`MAX_REFUSALS_LISTED`); "" when none
    was refused or the method gives no verdict."""
    from studies.common import one_line

    acc = df[(df.metric == "accepted") & (df.value <= 0.5)] if "metric" in df else df[:0]
    if acc.empty:
        return ""
    acc = acc.assign(reason=acc["reason"].fillna("").astype(str) if "reason" in acc else "")
    lines = [f"- {r['case']}: {one_line(r['reason'], 400) or '(no reason recorded)'}"
             for _, r in acc.head(MAX_REFUSALS_LISTED).iterrows()]
    more = len(acc) - MAX_REFUSALS_LISTED
    if more > 0:
        lines.append(f"- and {more} more (`results.csv`: metric `accepted`, column `reason`)")
    return (f"The method's verdict refused {len(acc)} case(s); its reasons:\n\n"
            + "\n".join(lines))


def time_markdown(df: pd.DataFrame) -> str:
    """The method's wall time per case (median, range), and the cases whose time is over
    3 times the median: a worker's first case includes its one-time start-up (imports,
    loading or compiling numba kernels: 155 s on a clone whose kernels were never compiled,
    a held-out review read it as the method's time)."""
    t = df[df.metric == "time"] if "metric" in df else df[:0]
    if t.empty:
        return ""
    med = float(t["value"].median())
    slow = t[t["value"] > 3 * med]
    text = (f"The method's wall time per case (`time` in results.csv): median {med:.2f} s, "
            f"{t['value'].min():.2f}-{t['value'].max():.2f} s over {len(t)} case(s).")
    if not slow.empty:
        text += (" Over 3 times the median: " + ", ".join(
            f"{r['case']} {r['value']:.1f} s" for _, r in slow.head(10).iterrows())
                 + ". A worker's first case includes its one-time start-up (imports, the "
                 "numba kernels loaded or compiled), which its later cases do not pay: "
                 "judge the method's speed by the median.")
    return text


def trial(tr) -> list[dict]:
    """A runner trial: case ``tr.params['case']`` of the dataset ``tr.scene``."""
    return score_case(Path(tr.scene) / tr.params["case"], tr.params["method"])


def missing_cases(dataset) -> list[str]:
    """The cases ``dataset.json`` lists that the folder does not hold (a ``testbed
    generate`` interrupted before it wrote them, or a case folder removed), in order."""
    from testbed.dataset import INDEX_FILE, list_cases

    index = Path(dataset) / INDEX_FILE
    try:
        listed = json.loads(index.read_text()).get("cases", [])
    except (OSError, ValueError, AttributeError):
        return []
    if not isinstance(listed, list) or not all(isinstance(c, str) for c in listed):
        raise ValueError(f"{index}: 'cases' must be a list of case folder names, got "
                         f"{listed!r:.80}")
    have = {c.name for c in list_cases(dataset)}
    return [str(c) for c in listed if str(c) not in have]


def _dataset_identity(dataset: Path) -> str:
    """What a dataset is, for the score's trials: its scene's digest and seed (from
    ``dataset.json``: a dataset moved or copied is the same), else its folder."""
    try:
        index = json.loads((dataset / "dataset.json").read_text())
        return f"the dataset of scene {index['scene_sha256'][:12]}, seed {int(index['seed'])}"
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return str(dataset.resolve())


def dataset_scene_warnings(scene, seed: int) -> list[str]:
    """:func:`studies.end_to_end.scene_warnings` of a dataset's scene (as its cases record
    it) at its seed; advisory: when they cannot be computed (e.g. a user mesh that is no
    longer where the scene names it), one line says so. A held-out review: a dataset of a CT of the
    proximal end only scored distal pins tens of mm off without a word, where testbed run
    and the studies name the missing slices."""
    from studies.end_to_end import scene_warnings

    if scene is None or getattr(scene.scene, "kind", "") != "operating_room":
        return []
    try:
        return scene_warnings(scene, int(seed))
    except Exception as exc:  # noqa: BLE001 - advisory: the scores stand without it
        # said, not dropped (a review: a user mesh moved since generate lost them silently)
        return [f"the scene's warnings could not be computed from the scene the cases "
                f"record ({' '.join(str(exc).split())[:200]}); the scores stand"]


def score_dataset(dataset, out, *, method: str = DEFAULT_METHOD, workers: int = 1,
                  scheduler=None, progress: bool = True,
                  timeout_s: float | None = None, retry_failed: bool = False) -> Path:
    """Score ``method`` on every case of ``dataset``; writes ``out/results.csv`` and
    ``out/report.md``; returns ``out``. Rerunning into the same ``out`` resumes.
    ``timeout_s``: a case whose method still runs after this many seconds is a failed case
    (its worker process killed), not a hung command (``testbed score --timeout``);
    ``retry_failed``: on a rerun, the cases stored as failed are scored again (``testbed
    score --retry-failed``)."""
    from studies.common import (
        SCORE_PREFIX,
        StudyContext,
        check_out_folder,
        finish_study,
        markdown_table,
        report_scene_warnings,
    )
    from studies.end_to_end import views_lost_markdown
    from studies.runner import code_fingerprint, fingerprint, make_trials, run_trials
    from testbed.dataset import list_cases

    dataset = Path(dataset)
    if not dataset.is_dir():
        raise ValueError(f"{dataset}: no such dataset folder")
    cases = list_cases(dataset)
    if not cases:
        raise ValueError(f"{dataset}: holds no case (case_*/case.json); make one with "
                         "testbed generate")
    fn = load_method(method)  # refuse a bad --method before any work
    out = Path(out)
    # the trials' owner names the dataset too: a folder scored on another dataset with the
    # same method was taken and its results replaced (a review)
    name = SCORE_PREFIX + method
    study = f"{name} of {_dataset_identity(dataset)}"
    check_out_folder(out, name, study=study)
    params = [{"case": c.name, "method": method} for c in cases]
    # what the scores read besides the names: the dataset's files that say what each case
    # is, and the method's source (a dataset regenerated, or a method edited, under the same
    # names is scored again, not taken from trials.sqlite)
    try:
        source = inspect.getsourcefile(fn) if fn is not None else None
    except TypeError:  # a compiled callable: its name alone
        source = None
    # ...each trial by its own case's record: a case added to the dataset, or one written
    # again, is scored alone (one fingerprint of every case.json scored them all again)
    # ...and the code that runs and scores it: reglib (the default method, or one a user's
    # method calls), testbed (the loader), studies (the scoring); "reglib" has no source
    # file of its own, and an edited reglib was scored from the database (a review)
    method_files = [source] if source else []
    code = code_fingerprint()
    trials = [dataclasses.replace(t, fingerprint=fingerprint(texts=[code],
                                                             files=[c / "case.json",
                                                                    *method_files]))
              for t, c in zip(make_trials(str(dataset.resolve()), 0, params), cases,
                              strict=True)]
    from testbed.dataset import load

    # the report's scene: from the first case that can be read (a broken case is a failed
    # trial, reported below, and must not lose the others' results); none: refused before
    # the work
    scene, problems = None, []
    for c in cases:
        try:
            _, truth0 = load(c)
            scene = parse_stored_scene(truth0.meta.get("truth", truth0.meta)["scene"],
                                       source=str(c))
            break
        except (OSError, ValueError, KeyError) as exc:
            problems.append(f"{c.name}: {exc}")
    if scene is None:
        gone = missing_cases(dataset)
        raise ValueError(f"{dataset}: no case can be read ({'; '.join(problems)[:300]})"
                         + (f"; dataset.json lists {', '.join(gone[:5])}"
                            + (f" and {len(gone) - 5} more" if len(gone) > 5 else "")
                            + ", which the folder lacks (renamed or removed?)" if gone else ""))
    # another's method runs in a worker process even alone: one that calls os._exit or
    # crashes ended the command with exit 0 (or 139) and no results (a review). Its workers
    # are spawned, which start from this process's sys.path (where load_method found the
    # method's module), not forked from a server started before it
    user = method != DEFAULT_METHOD
    df = run_trials(trial, trials, out_dir=out, workers=workers, scheduler=scheduler,
                    progress=progress, isolate=user, mp_context="spawn" if user else None,
                    timeout_s=timeout_s, study=study, retry_failed=retry_failed)
    reused = int(df.attrs.get("skipped", 0))
    reuse_note = ""
    if reused:
        # a method's source and the cases' files are in the trials' keys; what else the
        # method reads (an estimates file, a helper module, a model's weights) is not, and a
        # review's estimates file changed under it was scored from the database silently
        reuse_note = (f"{reused} of {len(cases)} case(s) taken from {out / 'trials.sqlite'}, "
                      "scored before with the same case files, method source and reglib / "
                      "testbed / studies code; what the method reads elsewhere is not "
                      "compared: delete that file to score them again")
        print(f"testbed score: {reuse_note}", file=sys.stderr)
    # the seed the cases were drawn from, as they record it (dataset.json's, edited, was
    # shown in its place, a review); dataset.json's when the case does not say
    try:
        seed = int(truth0.meta.get("truth", {}).get("dataset_seed",
                                                    truth0.meta.get("dataset_seed")))
    except (KeyError, TypeError, ValueError):
        try:
            seed = int(json.loads((dataset / "dataset.json").read_text()).get("seed", 0))
        except (OSError, ValueError, TypeError, AttributeError):
            seed = 0
    ctx = StudyContext(name=name, out=out, scene_path=dataset, scene=scene,
                       seed=seed, workers=workers, scheduler=scheduler)
    report_scene_warnings(ctx, dataset_scene_warnings(scene, seed),
                          "the scene the cases were generated from (its first case)")
    pe = df[df.metric == "pin_error"]
    if not pe.empty:
        t = pe.groupby("pin")["value"].agg(["mean", "median", "max"]).reset_index()
        per_case = pe.pivot_table(index="case", columns="pin", values="value").reset_index()
        verdict = df[df.metric.isin(["accepted", "converged"])].pivot_table(
            index="case", columns="metric", values="value")
        n_accepted = int(verdict["accepted"].sum()) if "accepted" in verdict else None
        if len(verdict):   # reglib's own method says whether it trusts each result
            per_case = per_case.merge(
                verdict.apply(lambda c: c.map(lambda v: "yes" if v > 0.5 else "no")
                              ).reset_index(), on="case",
                how="left")
        scored = pe["case"].nunique()
        ctx.report("Pin errors (mm)", f"Method `{method}` on {scored} case(s) of "
                   f"`{dataset}`" + (f" ({len(cases) - scored} of {len(cases)} failed: see "
                                    "'Failed cases')" if scored < len(cases) else "")
                   + "; starts as `testbed run` draws them."
                   + (f" The method's verdict accepted {n_accepted} of {len(verdict)} (the "
                      "means are over all)." if n_accepted is not None else "")
                   + (f" {reuse_note[0].upper()}{reuse_note[1:]}." if reuse_note else "")
                   + "\n\n"
                   + markdown_table(t, ".3f") + "\n\n" + markdown_table(per_case, ".3f"))
    timing = time_markdown(df)
    if timing:
        ctx.report("Time", timing)
    refused = refusals_markdown(df)
    if refused:
        ctx.report("Refused cases", refused)
    lost = views_lost_markdown(df)
    if lost:
        ctx.report("Views left out", lost)
    failures = df.attrs.get("failures", {})
    if failures:
        ctx.report("Failed cases", "\n".join(
            f"- {cases[k].name if 0 <= k < len(cases) else f'trial {k}'}: {v}"
            for k, v in failures.items()))
    missing = missing_cases(dataset)
    if missing:
        ctx.report("Missing cases", f"`dataset.json` lists {len(missing)} case(s) that the "
                   f"folder does not hold, not scored: {', '.join(missing[:20])}"
                   + (", ..." if len(missing) > 20 else "")
                   + " (`testbed generate` with the same scene, seed and --out completes it)")
    finish_study(ctx, df if len(df) else pd.DataFrame(columns=["trial", "metric", "value",
                                                               "unit"]))
    return out
