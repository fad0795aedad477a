"""The ``testbed`` command: ``run``, ``study``, ``generate``, ``score``, ``render``, ``bench``,
``scenes``.

One rule for every sub-command: a usage or input error (a bad option, a scene file or field,
an ``--out`` that cannot be written, a scene of the wrong kind, an infeasible acquisition)
exits with status 2 and ONE line on standard error that names the file, field or option and
what was expected; never a traceback (set ``TESTBED_DEBUG=1`` to see one). ``--out`` is checked
before any work. A failure after the computation never loses the result: it is printed
first, then the error is reported (status 1). An unexpected error exits 1 with one line.

Imports are lazy, so that ``testbed --help`` is fast and prints no library banner.
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import json
import math
import os
import re
import sys
from pathlib import Path

from studies import numerics

__all__ = ["UsageError", "build_parser", "main"]

PROG = "testbed"


class UsageError(Exception):
    """A usage or input error: exit 2 with this one-line message."""


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # one line, exit 2 (argparse prints usage + message)
        raise UsageError(f"{self.prog}: {message} (see {self.prog} --help)")


def _one_line(msg: str) -> str:
    """``msg`` on one line: its lines joined by "; ", each dropping the ``file: `` prefix the
    first line already gives (a scene's problems each name the file, for readers of the
    multi-line message; on one line the path came back before every field, a review)."""
    lines = [ln.strip() for ln in str(msg).strip().splitlines() if ln.strip()]
    if len(lines) > 1 and ": " in lines[0]:
        prefix = lines[0].split(": ", 1)[0] + ": "
        lines = lines[:1] + [ln.removeprefix(prefix) for ln in lines[1:]]
    return "; ".join(lines)


# --------------------------------------------------------------------------- argument types
#: testbed generate's largest --cases (a case is about 60 MB and 10 s: 10,000 is 600 GB)
MAX_CASES = 10_000


#: the most runs more of a trial whose worker was lost (a trial that kills its worker
#: every time would otherwise be run alone as often as asked, e.g. 1e12 times)
MAX_RETRIES = 100
_CASES_WHY = ("a case is about 60 MB of disk and 10 s of CPU; split the work over several "
              "--out folders")


def _int_at_least(lo: int, what: str, at_most: int | None = None, why: str = _CASES_WHY):
    def parse(text):
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer >= {lo} for {what}, got "
                                             f"{text!r}") from None
        if v < lo:
            raise argparse.ArgumentTypeError(f"expected an integer >= {lo} for {what}, got {v}")
        if at_most is not None and v > at_most:
            raise argparse.ArgumentTypeError(
                f"expected at most {at_most} for {what}, got {v} ({why})")
        return v
    return parse


def _workers(text):
    """``--workers``: an integer from 1 to :func:`_max_workers` (each worker is a process
    with its own simulator: beyond a few per core they only compete for the cores)."""
    v = _int_at_least(1, "--workers")(text)
    most = _max_workers()
    if v > most:
        raise argparse.ArgumentTypeError(
            f"expected at most {most} for --workers on this machine ({os.cpu_count()} "
            f"core(s)), got {v}; a cluster's workers come with --scheduler")
    return v


#: ``testbed score``'s default time limit per case (s): reglib takes about a second, a
#: method that has not answered in ten minutes is taken as hung (``--timeout``)
SCORE_TIMEOUT_S = 600.0


def _seconds(text: str) -> float:
    """``--timeout``: seconds, a finite number >= 0 (0: no limit)."""
    try:
        v = float(text)
    except ValueError:
        v = float("nan")
    if not math.isfinite(v) or v < 0:
        raise argparse.ArgumentTypeError(f"expected a number of seconds >= 0 (0: no limit), "
                                         f"got {text!r}")
    return v


def _path(text: str) -> Path:
    """A path argument (``--out``, a dataset folder): an empty one was taken as the current
    folder, and a review's ``--out ""`` wrote a study's files into the repository."""
    if not text.strip():
        raise argparse.ArgumentTypeError("expected a path, got an empty string")
    return Path(text)


def _max_workers() -> int:
    return max(64, 8 * (os.cpu_count() or 1))


def _folder_problem(path: Path) -> str | None:
    """Why ``path`` cannot be used as an output folder (it is made if missing), or None."""
    if path.exists() and not path.is_dir():
        return "exists and is not a folder"
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        return f"cannot create the folder ({exc.strerror or exc})"
    if not _can_write_in(path):
        return "the folder is not writable"
    return None


def _out_folder(path: Path, option: str = "--out") -> Path:
    """An output folder: created if missing; refused when it is a file or cannot be written."""
    path = Path(path)
    problem = _folder_problem(path)
    if problem:
        raise UsageError(f"{option} {path}: {problem}")
    return path


def _can_write_in(folder: Path) -> bool:
    """True if a file can be made in ``folder``: tried, as os.access answers yes to root on
    /proc or a read-only mount."""
    import tempfile

    try:
        with tempfile.TemporaryFile(dir=folder):
            return True
    except OSError:
        return False


def _creatable_folder(path: Path, option: str = "--out") -> Path:
    """An output folder that the command makes itself: an existing writable folder, or a
    path whose nearest existing ancestor is a writable folder. Nothing is created here."""
    path = Path(path)
    if path.exists():
        if not path.is_dir():
            raise UsageError(f"{option} {path}: exists and is not a folder")
        if not _can_write_in(path):
            raise UsageError(f"{option} {path}: the folder is not writable")
        return path
    anc = path.absolute().parent
    while not anc.exists() and anc != anc.parent:
        anc = anc.parent
    if not anc.is_dir():
        raise UsageError(f"{option} {path}: cannot create the folder ({anc} is a file)")
    if not _can_write_in(anc):
        raise UsageError(f"{option} {path}: cannot create the folder ({anc} is not writable)")
    return path


def _out_file(path: Path, suffix: str, option: str = "--out") -> Path:
    """An output file with ``suffix``: its folder must exist or be creatable, and writable."""
    path = Path(path)
    if path.is_dir():
        raise UsageError(f"{option} {path}: is a folder, expected a {suffix} file name")
    if path.suffix.lower() != suffix:
        raise UsageError(f"{option} {path}: expected a {suffix} file name")
    folder = path.parent if str(path.parent) else Path(".")
    problem = _folder_problem(folder)
    if problem:  # the file asked for, then what is wrong with its folder
        raise UsageError(f"{option} {path}: cannot write there ({folder}: {problem})")
    return path


def _quiet_pybullet() -> None:
    """pybullet imported without its banner (:func:`studies.threads.quiet_pybullet`)."""
    from studies.threads import quiet_pybullet

    quiet_pybullet()


#: the scene file of the running command (set by _scene): named in an infeasible-scene error
_scene_path: Path | None = None


def _check_scheduler(args, command: str) -> None:
    """--workers and --scheduler exclude each other; an unreachable scheduler fails here,
    within studies.runner.SCHEDULER_TIMEOUT_S (10 s), before any work."""
    if args.scheduler is None:
        return
    if args.workers != 1:
        raise UsageError(f"{PROG} {command}: give --workers or --scheduler, not both")
    from studies.runner import _client

    _client(args.scheduler).close()


def _scene(arg):
    global _scene_path
    _quiet_pybullet()
    from testbed.scene import find_scene, load_scene

    path = find_scene(arg)
    scene = load_scene(path)
    _scene_path = path
    return path, scene


def _names_scene_file(exc: Exception, msg: str) -> str:
    """An error about the scene found after loading (e.g. ``testbed.workspace``'s
    WorkspaceError: a view the robot cannot reach) gets the scene file in front."""
    if _scene_path is None or str(_scene_path) in msg:
        return msg
    if type(exc).__name__ in ("WorkspaceError", "SceneError"):
        return f"{_scene_path}: {msg}"
    # a ValueError that names a field of a scene section ("phantom: ...", "phantom.mesh_path:
    # ...", "views[2] ...") is about the scene file too (a review: the file was missing)
    if re.match(r"(phantom|robot|fluoroscope|patient|ct|operator|instruments|views|workspace"
                r"|scene)(\.|\[|:| )", msg):
        return f"{_scene_path}: {msg}"
    return msg


# --------------------------------------------------------------------------- commands
def cmd_run(args) -> int:
    path, scene = _scene(args.scene)
    out = _out_folder(args.out) if args.out is not None else None
    if out is None and scene.scene.kind == "synthetic":
        # the synthetic job writes its two studies: to runs/<name> unless --out says where
        out = Path("runs") / scene.scene.name
        problem = _folder_problem(out)
        if problem:
            raise UsageError(f"{path}: a synthetic scene's run writes its studies to {out} "
                             f"when no --out is given: {problem}; give --out DIR")
    from studies.main_job import format_result, run_main_job

    result = run_main_job(scene, scene_path=path, seed=args.seed, out=out,
                          progress=sys.stderr.isatty() and not args.json)
    error = result.pop("write_error", None)
    if args.json:
        print(json.dumps(_finite_or_null(result), indent=2, default=float))
    else:
        print(format_result(result))
    if error:
        print(f"{PROG}: {error}", file=sys.stderr)
        return 1
    return 0


def cmd_study(args) -> int:
    _quiet_pybullet()
    from studies import available_studies, run_study

    if args.list or not args.name:
        for name, doc in available_studies().items():
            print(f"{name:16s} {doc}")
        return 0
    known = available_studies()
    if args.name not in known:
        raise UsageError(f"{PROG} study: unknown study {args.name!r}; known: "
                         f"{', '.join(known)}")
    if args.out is None:
        raise UsageError(f"{PROG} study: --out DIR is required")
    global _scene_path
    if args.scene is not None:  # a refusal of the scene after loading names its file
        from testbed.scene import find_scene, load_scene

        _scene_path = find_scene(args.scene)
        scene = load_scene(_scene_path)   # a malformed scene is refused before --out is made
        if scene.scene.kind == "operating_room":
            # ...and one whose world cannot be built (a user mesh that cannot be read, a view
            # the C-arm or the robot cannot take), as testbed run refuses it: exit 2 naming
            # the field, not a failed trial per case after the work has started
            from testbed.ct import plan_scan
            from testbed.simulate import checked_world

            case_scene, world, _ = checked_world(
                scene, scene.scene.seed if args.seed is None else args.seed)
            plan_scan(world.phantom, case_scene.ct)   # ...and a CT it cannot scan
    made = not Path(args.out).exists()
    out = _out_folder(args.out)
    try:
        from studies import check_serial

        check_serial(args.name, args.workers, args.scheduler)
        _check_scheduler(args, "study")
        run_study(args.name, out, scene=args.scene, seed=args.seed, quick=args.quick,
                  workers=args.workers, scheduler=args.scheduler, retries=args.retries,
                  progress=sys.stderr.isatty(), retry_failed=args.retry_failed)
    except BaseException:
        if made and out.is_dir() and not any(out.iterdir()):
            out.rmdir()   # refused before any result: leave no empty folder behind
        raise
    print(f"wrote {out / 'results.csv'} and {out / 'report.md'}")
    return _failed_trials(out)


def _failed_trials(out: Path) -> int:
    """After a study or a score: 1 with a line on stderr when trials failed (an exception:
    its message is in report.md), else 0. The results of the others are written."""
    import pandas as pd

    try:
        df = pd.read_csv(out / "results.csv", usecols=["trial", "metric"])
    except (OSError, ValueError):
        return 0
    # a study's summary rows (trial -1) are no trial; table1's trials are text labels
    # ("clean-20-0"), which a comparison with 0 failed on (every table1 run ended in an
    # internal error after its results were written, a review)
    df = df[~(pd.to_numeric(df.trial, errors="coerce") < 0)]
    failed = df.loc[df.metric == "failed", "trial"].nunique()
    if not failed:
        return 0
    print(f"{PROG}: {failed} of {df.trial.nunique()} trial(s) failed (the error of each is in "
          f"{out / 'report.md'}; the others' results are written; the same command with "
          "--retry-failed runs the failed ones again)", file=sys.stderr)
    return 1


def cmd_generate(args) -> int:
    path, scene = _scene(args.scene)
    if scene.scene.kind != "operating_room":
        raise UsageError(f"{path}: scene kind {scene.scene.kind!r}: testbed generate needs an "
                         "operating_room scene with [[views]] (e.g. experiment2)")
    out = _creatable_folder(args.out)
    from studies.end_to_end import sim_warnings
    from testbed.generate import generate_command

    warnings = []      # what testbed run says of the scene, from case 0 when this run makes it

    def first_case(i, sim):
        if i == 0:
            warnings.extend(sim_warnings(sim))

    dirs = generate_command(scene, scene_path=path, cases=args.cases, out=out, seed=args.seed,
                            progress=sys.stderr.isatty(), on_case=first_case)
    # (a rerun keeps the complete cases: it may write none of them)
    print(f"{len(dirs)} case(s) complete in {out}")
    for w in warnings:
        print(f"{PROG} generate: warning: {w}", file=sys.stderr)
    if not scene.workspace.check:   # as testbed run and the score report say it (a review)
        print(f"{PROG} generate: {path.name} opts out of the workspace check ([workspace] "
              "check = false): its acquisitions were not checked for collisions",
              file=sys.stderr)
    if len(dirs) > 1 and not scene.patient.varies:
        print(f"testbed generate: every case lies where {path.name}'s [patient] puts it (one "
              "ct2robot for all: a method that returns that placement scores 0 mm); set "
              "[patient] position_sd_mm and rotation_sd_deg for a dataset whose truth varies "
              "from case to case", file=sys.stderr)
    return 0


def cmd_score(args) -> int:
    _quiet_pybullet()
    from studies.score import load_method, missing_cases, score_dataset
    from testbed.dataset import list_cases

    dataset = Path(args.dataset)
    if dataset.exists() and not dataset.is_dir():
        raise UsageError(f"{dataset}: is a file, not a dataset folder (give the folder that "
                         f"{PROG} generate --out wrote)")
    if not dataset.is_dir():
        raise UsageError(f"{dataset}: no such dataset folder")
    try:
        load_method(args.method)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    if args.scheduler is not None and args.timeout:
        raise UsageError("--timeout: a time limit per case needs local workers; with "
                         "--scheduler set one on the Dask cluster instead")
    _check_scheduler(args, "score")
    timeout = (None if args.scheduler is not None or args.timeout == 0 else
               SCORE_TIMEOUT_S if args.timeout is None else args.timeout)
    if not list_cases(dataset):     # before --out is made
        if (dataset / "case.json").is_file():
            raise UsageError(f"{dataset}: is one case; give the dataset folder that holds it "
                             f"({dataset.parent})")
        raise UsageError(f"{dataset}: holds no case (case_*/case.json); make one with "
                         f"{PROG} generate")
    if Path(args.out).resolve().is_relative_to(dataset.resolve()):
        raise UsageError(f"--out {args.out}: inside the dataset {dataset}; the scores go to a "
                         "folder of their own (the dataset stays as generate wrote it)")
    missing = missing_cases(dataset)   # a malformed dataset.json: refused before the work
    made = not Path(args.out).exists()
    out = _out_folder(args.out)
    try:
        score_dataset(dataset, out, method=args.method, workers=args.workers,
                      scheduler=args.scheduler, progress=sys.stderr.isatty(),
                      timeout_s=timeout, retry_failed=args.retry_failed)
    except BaseException:
        if made and out.is_dir() and not any(out.iterdir()):
            out.rmdir()   # refused before any result (no case can be read): no folder left
        raise
    print(f"wrote {out / 'results.csv'} and {out / 'report.md'}")
    status = _failed_trials(out)
    if missing:
        print(f"{PROG}: {dataset}/dataset.json lists {len(missing)} case(s) the folder does "
              f"not hold ({', '.join(missing[:5])}{', ...' if len(missing) > 5 else ''}): not "
              "scored; testbed generate with the same scene, seed and --out completes the "
              "dataset", file=sys.stderr)
        status = 1
    return status


def _view_choice(text):
    """``--view``: an index (an integer >= 0) or a view's name, resolved against the scene
    by :func:`_view_index` (a held-out review: only an index was taken, where every other
    command and message names the views)."""
    text = str(text).strip()
    if text.lstrip("+-").isdigit():
        return _int_at_least(0, "--view")(text)
    if not text:
        raise argparse.ArgumentTypeError("expected a view name or index for --view, got ''")
    return text


def _view_index(scene, view) -> int:
    """``--view``'s index in ``scene`` (a name looked up among ``views[].name``)."""
    if isinstance(view, int):
        return view
    names = [v.name for v in scene.views]
    if view not in names:
        raise UsageError(f"--view {view!r}: the scene {scene.scene.name!r} has no view of that "
                         f"name; its views: {', '.join(names) or 'none'} (or give an index, "
                         "0-based)")
    return names.index(view)


def cmd_render(args) -> int:
    path, scene = _scene(args.scene)
    args.view = _view_index(scene, args.view)
    out = _out_file(args.out, ".png")
    import cv2

    from testbed.fluoroscope import render_view
    from testbed.simulate import case_world

    # the world of `testbed run` with the same seed: with [phantom] shape_variation > 0 the
    # femur is drawn from shape_seed and the case's seed, as every study case draws its own
    seed = scene.scene.seed if args.seed is None else args.seed
    case_scene, world = case_world(scene, seed)
    bodies = world.bodies
    if case_scene.patient.moves and 0 <= args.view < len(case_scene.views):
        # the femur where that view saw it, as testbed run simulates it
        from testbed.simulate import case_streams, view_bodies, view_poses

        pose = view_poses(case_scene, world.ct2robot, case_streams(seed)["motion"])[args.view]
        bodies = view_bodies(world, pose)
    frame = render_view(scene, args.view, seed=seed, bodies=bodies)
    _render_workspace_warning(case_scene, world)
    if not cv2.imwrite(str(out), frame.image_u8):
        raise UsageError(f"--out {out}: could not write the image")
    print(f"wrote {out}")
    return 0


def _render_workspace_warning(scene, world) -> None:
    """A line on stderr when the acquisition that ``render`` draws is one ``testbed run``
    refuses, or that was not checked (a review: both were drawn without a word)."""
    from testbed.workspace import WorkspaceError, require_feasible

    if not scene.workspace.check:
        print("warning: the workspace was not checked ([workspace] check = false): this "
              "acquisition may not be physically possible", file=sys.stderr)
        return
    try:
        require_feasible(scene, world)
    except WorkspaceError as exc:
        print(f"warning: {_one_line(str(exc))} (testbed run refuses this scene; the frame is "
              "drawn as asked)", file=sys.stderr)


def cmd_bench(args) -> int:
    _quiet_pybullet()
    from studies.bench.suite import format_table, run_bench

    rows = run_bench(quick=args.quick, only=args.only, progress=not args.json)
    print(json.dumps(_finite_or_null(rows), indent=2, allow_nan=False) if args.json
          else format_table(rows))
    return 0


def cmd_scenes(args) -> int:
    import tomllib

    if getattr(args, "show", None) is not None:
        # what a scene file leaves out is the defaults': the scene as the simulator reads it
        # (a review, h97: no command showed it)
        _, scene = _scene(args.show)
        print(json.dumps(_finite_or_null(scene.model_dump(mode="json")), indent=2))
        return 0
    _quiet_pybullet()
    from testbed.scene import named_scene_files, scenes_dir, scenes_dir_problem

    what = scenes_dir_problem()
    if what:
        hint = "a file" if what == "is not a folder" else "a missing folder"
        raise UsageError(f"the folder of named scenes {scenes_dir()} {what} (is "
                         f"TESTBED_SCENES set to {hint}?)")
    for p in named_scene_files():
        try:
            meta = tomllib.loads(p.read_bytes().decode("utf-8-sig")).get("scene", {})
            desc = str(meta.get("description", "")) if isinstance(meta, dict) else ""
        except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
            desc = f"(unreadable: {_one_line(str(exc))})"
        print(f"{p.stem:22s} {desc}")
    return 0


def _finite_or_null(obj):
    """``obj`` with every non-finite float (NaN, inf) as None: strict JSON has neither."""
    import math

    if isinstance(obj, dict):
        return {k: _finite_or_null(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_finite_or_null(v) for v in obj]
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("xray-reg-testbed")
    except PackageNotFoundError:
        return "unknown (not installed)"


def _scene_arguments(parser, help_text: str) -> None:
    """The scene of ``run``, ``generate`` and ``render``: positional, or ``--scene`` as the
    studies take it (:func:`_merge_scene` joins the two)."""
    parser.add_argument("scene", nargs="?", default=None, help=help_text)
    parser.add_argument("--scene", dest="scene_option", default=None, metavar="SCENE",
                        help="the same as the positional scene")


def _merge_scene(args) -> None:
    """``args.scene`` from the positional scene or ``--scene``; both, naming different
    scenes, are a usage error."""
    option = getattr(args, "scene_option", None)
    if option is None:
        return
    if args.scene is not None and args.scene != option:
        raise UsageError(f"{PROG} {args.command}: two scenes given ({args.scene!r} and "
                         f"--scene {option!r}); give one")
    args.scene = option


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog=PROG, description="Simulation testbed for CT to X-ray registration for a "
                "surgical robot (after Gueziec et al., IEEE TMI 1998).")
    p.add_argument("--version", action="store_true", help="print the version and exit")
    sub = p.add_subparsers(dest="command", parser_class=_Parser)
    seed = _int_at_least(0, "--seed")

    r = sub.add_parser("run", help="the main job on a scene (default scene: experiment2)")
    _scene_arguments(r, "scene file or name")
    r.add_argument("--json", action="store_true", help="print one JSON object")
    r.add_argument("--seed", type=seed, default=None, help="override the scene's seed")
    r.add_argument("--out", type=_path, default=None,
                   help="folder for the overlay figures (none without it); a synthetic "
                   "scene's run writes its two studies there (default runs/<scene name>)")
    r.set_defaults(func=cmd_run)

    s = sub.add_parser("study", help="run a study and write results.csv, report.md, figures")
    s.add_argument("name", nargs="?", help="study name (see --list)")
    s.add_argument("--out", type=_path, help="output folder (required with a study name)")
    s.add_argument("--scene", default=None, help="scene file or name (study default if none)")
    s.add_argument("--seed", type=seed, default=None, help="override the study's seed")
    s.add_argument("--quick", action="store_true", help="a small version (for smoke tests)")
    s.add_argument("--workers", type=_workers, default=1,
                   help="worker processes")
    s.add_argument("--scheduler", default=None,
                   help="run trials on a Dask cluster: scheduler address tcp://HOST:PORT")
    s.add_argument("--retries", type=_int_at_least(
                       0, "--retries", MAX_RETRIES, "each retry runs a trial whose worker "
                       "died once more, alone"), default=2,
                   help="runs more of a trial whose worker was lost (default 2)")
    s.add_argument("--retry-failed", action="store_true",
                   help="on a rerun, run again the trials stored as failed (kept otherwise)")
    s.add_argument("--list", action="store_true", help="list the studies")
    s.set_defaults(func=cmd_study)

    g = sub.add_parser("generate", help="write a synthetic dataset")
    _scene_arguments(g, "scene file or name (default: experiment2)")
    g.add_argument("--cases", type=_int_at_least(1, "--cases", at_most=MAX_CASES), default=1,
                   help="number of cases (default 1); a rerun resumes")
    g.add_argument("--out", required=True, type=_path,
                   help="the dataset folder (new, empty, or a dataset of the same scene and "
                   "seed)")
    g.add_argument("--seed", type=seed, default=None,
                   help="the dataset's seed (default: the scene's); case i is case i of it")
    g.set_defaults(func=cmd_generate)

    c = sub.add_parser("score", help="score a registration method on a generated dataset")
    c.add_argument("dataset", type=_path, help="a folder written by testbed generate")
    c.add_argument("--method", default="reglib",
                   help="pkg.module:function (Observation, initial 4x4) -> 4x4 ct2robot; "
                   "default: reglib.estimate")
    c.add_argument("--out", required=True, type=_path, help="output folder (outside the "
                   "dataset)")
    c.add_argument("--workers", type=_workers, default=1, help="worker processes")
    c.add_argument("--scheduler", default=None,
                   help="run cases on a Dask cluster: scheduler address tcp://HOST:PORT")
    c.add_argument("--timeout", type=_seconds, default=None, metavar="SECONDS",
                   help="a case whose method runs longer is a failed case, its worker "
                   f"stopped (default {SCORE_TIMEOUT_S:g} s with local workers; 0: no limit; "
                   "not with --scheduler)")
    c.add_argument("--retry-failed", action="store_true",
                   help="on a rerun, score again the cases stored as failed (a timeout, a "
                   "crash); kept otherwise")
    c.set_defaults(func=cmd_score)

    d = sub.add_parser("render", help="render one X-ray frame of a view to PNG")
    _scene_arguments(d, "scene file or name (default: experiment2)")
    d.add_argument("--view", type=_view_choice, default=0,
                   help="the view: its name (views[].name) or its index (0-based; default 0)")
    d.add_argument("--out", required=True, type=_path, help="a .png file")
    d.add_argument("--seed", type=seed, default=None,
                   help="the case seed (default: the scene's); the world of testbed run "
                   "--seed with the same value, its femur included")
    d.set_defaults(func=cmd_render)

    b = sub.add_parser("bench", help="measure every performance target")
    b.add_argument("--quick", action="store_true", help="fewer repeats (a smoke test)")
    b.add_argument("--json", action="store_true", help="print one JSON object")
    b.add_argument("--only", nargs="+", default=None, metavar="WORKLOAD",
                   help="only these workloads (keys of the JSON, e.g. frame_ms)")
    b.set_defaults(func=cmd_bench)

    n = sub.add_parser("scenes", help="list the named scenes")
    n.add_argument("--show", metavar="SCENE", default=None,
                   help="print SCENE (a named scene or a file) resolved, every default filled "
                   "in, as JSON (the resolved scene the reports and case.json record)")
    n.set_defaults(func=cmd_scenes)
    return p


#: BLAS/OpenMP thread counts set to 1 unless the environment sets them (read by the BLAS
#: when numpy is first imported, which the lazy imports leave until after this;
#: studies.numerics sets them with the rest of the numeric environment)
SINGLE_THREAD_VARS = numerics.SINGLE_THREAD_VARS
#: commands whose process simulates or estimates and then exits: their imports are frozen
#: out of the garbage collector's scans (studies.threads.freeze_work_modules); not when
#: main() is called in a longer-lived process (``argv`` given)
FREEZING_COMMANDS = ("run", "generate", "score")


def _check_environment() -> None:
    """Thread counts given in the environment must be positive integers (numba refused
    NUMBA_NUM_THREADS=0 inside a view's processing, and the message blamed the view)."""
    for var in ("NUMBA_NUM_THREADS", *SINGLE_THREAD_VARS):
        val = os.environ.get(var)
        if val is None:
            continue
        try:
            ok = int(val) >= 1
        except ValueError:
            ok = False
        if not ok:
            raise UsageError(f"environment: {var}={val!r}; expected a whole number of threads "
                             ">= 1 (or leave it unset)")


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised where the process is, so that it cleans up as after Ctrl-C (a
    generate's half-written case folder is removed; a study's finished trials are kept)."""


def _terminate_as_interrupt() -> None:
    """SIGTERM raises :class:`Terminated` in the main thread (a kill, a batch system's time
    limit): by default Python dies at once and left a generate's temporary case folder."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        return

    def handler(signum, frame):
        raise Terminated()

    try:
        signal.signal(signal.SIGTERM, handler)
    except (ValueError, OSError):  # not settable here: the default stays
        pass


def _interrupt_of(exc):
    from studies.runner import interrupt_of

    return interrupt_of(exc)


def _interrupted(exc: KeyboardInterrupt) -> int:
    """The line and exit status of an interrupt (130) or a SIGTERM (143)."""
    print(f"{PROG}: {'terminated' if isinstance(exc, Terminated) else 'interrupted'}",
          file=sys.stderr)
    return 143 if isinstance(exc, Terminated) else 130


def main(argv=None) -> int:
    global _scene_path
    _scene_path = None
    # One BLAS thread, and the AVX2 code on an x86 CPU that has more: the same seed gave
    # another result on another machine (studies.numerics); studies parallelise by process.
    numerics.apply()
    debug = bool(os.environ.get("TESTBED_DEBUG"))
    _terminate_as_interrupt()
    try:
        _check_environment()
        args = build_parser().parse_args(argv)
        _merge_scene(args)
        if args.version:
            print(f"{PROG} {_version()}")
            return 0
        if not getattr(args, "command", None):
            raise UsageError(f"{PROG}: a command is needed: run, study, generate, score, "
                             f"render, bench, scenes (see {PROG} --help)")
        from studies.threads import (
            freeze_before_exit,
            freeze_work_modules,
            hold_full_collections,
            single_threaded_kernels,
        )

        freezing = argv is None and args.command in FREEZING_COMMANDS
        with hold_full_collections() if freezing else contextlib.nullcontext():
            single_threaded_kernels()   # and OpenCV's threads off (studies/threads.py)
            if freezing:
                _quiet_pybullet()       # imported by the freeze: without its banner on stderr
                freeze_work_modules()   # a process that does the work and exits (threads.py)
        code = int(args.func(args) or 0)
        if freezing:
            freeze_before_exit()    # the exit's full collection scans none of it
        return code
    except UsageError as exc:
        msg = _one_line(str(exc))
        print(msg if msg.startswith(PROG) else f"{PROG}: {msg}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        return _interrupted(exc)
    except BrokenPipeError:
        # the reader of the output went away (``testbed scenes | head``): no error of ours;
        # stdout pointed at nothing so that the exit's flush does not fail again
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except OSError as exc:  # the disk or the file system, during the work
        stop = _interrupt_of(exc)
        if stop is not None:
            return _interrupted(stop)
        if debug:
            raise
        if exc.errno == errno.ENAMETOOLONG:    # an argument the file system cannot hold
            name = str(exc.filename or "")
            print(f"{PROG}: a path given is too long for the file system ({len(name):,} "
                  f"characters: {name[:60]!r}...)", file=sys.stderr)
            return 2
        where = f"{exc.filename}: " if exc.filename and str(exc.filename) not in str(exc) else ""
        print(f"{PROG}: {where}{_one_line(str(exc))}", file=sys.stderr)
        return 2 if isinstance(exc, FileNotFoundError) else 1  # a missing input file: 2
    except Exception as exc:
        from testbed.spec import SceneError

        stop = _interrupt_of(exc)   # Ctrl-C inside a compiled function: a SystemError
        if stop is not None:
            return _interrupted(stop)
        if debug:
            raise
        if isinstance(exc, SceneError | ValueError | FileNotFoundError):
            msg = _names_scene_file(exc, _one_line(str(exc)))
            print(msg if msg.startswith(f"{PROG} ") else f"{PROG}: {msg}", file=sys.stderr)
            return 2
        print(f"{PROG}: internal error: {type(exc).__name__}: {_one_line(str(exc))} "
              "(TESTBED_DEBUG=1 shows the traceback)", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
