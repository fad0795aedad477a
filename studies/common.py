"""What every study shares: the context it runs in, and the files it leaves behind.

``results.csv`` is long format (``trial, metric, value, unit`` + parameter columns);
``report.md`` starts with the provenance (study, scene file, seed, git commit, time, the command
that reproduces it and the numerical libraries' versions) and the
resolved scene, then the sections the study added, then the figures.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import re
import subprocess
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from testbed.scene import find_scene, load_scene, scenes_dir

if TYPE_CHECKING:   # pandas only in annotations: testbed run does not pay its import
    import pandas as pd

REQUIRED_COLUMNS = ("trial", "metric", "value", "unit")


def git_commit() -> str:
    """The project's git commit (with ``-dirty`` if the tree has changes), or ``unknown``."""
    root = Path(__file__).resolve().parents[1]
    try:
        sha = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True,
                             text=True, timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"],
                               cwd=root, capture_output=True, text=True, timeout=10).stdout
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    if not sha:
        return "unknown"
    return sha + ("-dirty" if dirty.strip() else "")


@dataclass
class StudyContext:
    """Where and how a study runs. ``rng`` is made from ``seed``; use ``spawn`` for trials."""

    name: str
    out: Path
    scene_path: Path
    scene: object
    seed: int
    quick: bool = False
    workers: int = 1
    scheduler: object = None
    sections: list = field(default_factory=list)
    figures: list = field(default_factory=list)

    def seeds(self, n: int) -> list[np.random.SeedSequence]:
        """``n`` independent child seeds of the study seed (same on any number of workers)."""
        return np.random.SeedSequence(self.seed).spawn(n)

    def report(self, heading: str, body: str) -> None:
        """Add a markdown section to ``report.md``."""
        self.sections.append((heading, body))

    def figure(self, filename: str, caption: str) -> Path:
        """Register a figure file (in ``out``) to be linked from the report; returns its path."""
        self.figures.append((filename, caption))
        return self.out / filename


def _enclosing_dataset(out) -> Path | None:
    """The index (``dataset.json`` of ``testbed generate``) or case file (``case.json``
    of a testbed case) of the folder that ``out`` is, or lies in; None when there is none."""
    try:
        here = Path(out).resolve()
    except (OSError, RuntimeError):
        return None
    for folder in (here, *here.parents):
        for name, key, value in (("dataset.json", "generator", "testbed generate"),
                                 ("case.json", "format", "xray-reg-testbed-case")):
            try:   # a file of that name that is not ours (a user's own dataset.json) is no
                with open(folder / name, encoding="utf-8") as f:   # dataset of ours
                    if json.load(f).get(key) == value:
                        return folder / name
            except (OSError, ValueError, AttributeError):
                continue
    return None


def check_out_folder(out, name: str, *, study: str | None = None) -> None:
    """ValueError when folder ``out`` holds the report of another study than ``name`` (or a
    ``report.md`` no study wrote), or the trials of another ``study`` (default ``name``; the
    name its ``run_trials`` records): running there would replace that study's results and
    report and leave its figures beside the new ones. The same study's folder resumes."""
    from studies.runner import DB_NAME, owner_conflict, stored_study

    dataset = _enclosing_dataset(out)
    if dataset is not None:
        # score refused this; a study wrote its results.csv, report and database among the
        # cases (a review)
        raise ValueError(f"--out {out}: inside the dataset of {dataset}; a study's results "
                         "go to a folder of their own (the dataset stays as generate wrote it)")
    owner, want = stored_study(out), name if study is None else study
    if owner_conflict(owner, want):
        # a study interrupted before its report leaves only its database: a review's other
        # study then ran there, replaced its results.csv and mixed both in trials.sqlite;
        # the same study of another scene or seed did the same (a review)
        # the stored run's own flags (studies.study_owner ends in ", quick" for --quick);
        # a review was told to add --quick to resume a run made without it
        quick = " and --quick" if owner.endswith(", quick") else " (without --quick)"
        scored = scored_method(owner) is not None
        again = ("the same testbed score of that dataset" if scored
                 else f"testbed study {owner.split(' ', 1)[0]} with that scene, seed{quick}")
        raise ValueError(f"--out {out}: holds the trials of {owner!r} ({DB_NAME}), not of "
                         f"{want!r}; give another folder (or run {again} with this --out to "
                         "resume it)")
    # what the study will write over: a folder of that name, or a file that cannot be
    # written (read-only, immutable), failed only after the whole study had run (a review)
    for path in (Path(out) / "results.csv", Path(out) / "report.md", Path(out) / DB_NAME,
                 *sorted(Path(out).glob("*.png"))):
        if path.is_dir() or (path.exists() and not os.access(path, os.W_OK)):
            raise ValueError(f"--out {out}: {path.name} cannot be replaced "
                             f"({'it is a folder' if path.is_dir() else 'not writable'}); "
                             "move it away or give another folder")
    report = Path(out) / "report.md"
    if owner is not None and not owner_conflict(owner, want):
        # the database names this very study: the folder is its own, and its report is
        # written again at the end, whatever is left of it now (a report cut short by a full
        # disk blocked the resume, and "give another folder" lost the stored trials)
        return
    if not report.is_file():
        # a results.csv beside no report and no trial database is no study's: a user's file
        # that the study would replace (a review: score --out on a folder of one's own
        # results overwrote them); a study interrupted before its report keeps its database
        if (Path(out) / "results.csv").is_file() and not (Path(out) / "trials.sqlite").exists():
            raise ValueError(f"--out {out}: holds a results.csv that no study wrote (no "
                             "report.md, no trials.sqlite beside it); give another folder")
        return
    try:
        with open(report, encoding="utf-8", errors="replace") as f:
            first = f.readline().strip()
    except OSError as exc:
        raise ValueError(f"--out {out}: cannot read its report.md ({exc.strerror})") from None
    m = re.fullmatch(r"# Study `(.+)`", first)
    if m is None:
        raise ValueError(f"--out {out}: holds a report.md that no study wrote (its first line "
                         f"{first[:60]!r}); give another folder")
    if m.group(1) != name:
        raise ValueError(f"--out {out}: holds the results of {m.group(1)!r} (report.md), not "
                         f"of {name!r}; give another folder, or the same command to resume")


def start_study(name, out, *, scene, seed=None, quick=False, workers=1,
                scheduler=None) -> StudyContext:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    # the trials' keys hold the scene's path: resolved, so that the same file typed from
    # another folder or as an absolute path resumes the study (each spelling ran every trial
    # again, a review)
    path = Path(os.path.abspath(find_scene(scene)))   # not resolve(): a link stays a link
    sc = load_scene(path)
    seed = sc.scene.seed if seed is None else int(seed)
    return StudyContext(name=name, out=out, scene_path=path, scene=sc, seed=seed,
                        quick=quick, workers=workers, scheduler=scheduler)


def nothing_finished(ctx: StudyContext, df: pd.DataFrame, heading: str) -> bool:
    """True when no trial of ``df`` finished (every row a failure, or no row): the report
    then says so under ``heading`` with each trial's error, and the study writes no table
    or figure (they would be made of nothing)."""
    from studies.runner import FAILED_METRIC

    if len(df) and (df["metric"] != FAILED_METRIC).any():
        return False
    failures = df.attrs.get("failures", {})
    # the errors themselves: once, under 'Failed trials' (finish_study); they were listed
    # here and there too (a review)
    ctx.report(heading, "No trial finished" + (
        f": {len(failures)} failed (their errors under 'Failed trials')." if failures
        else "."))
    return True


def check_results(df: pd.DataFrame) -> None:
    missing = [c for c in REQUIRED_COLUMNS if c not in df.columns]
    if missing:
        raise ValueError(f"study results lack the columns {missing}")


def cell_text(x) -> str:
    """A results cell as text: a whole float as an integer (a case read back beside NaNs
    is a float, and a report read "case 0.0"), an empty or NaN cell as ""."""
    if isinstance(x, float):
        return "" if np.isnan(x) else str(int(x)) if x.is_integer() else str(x)
    return "" if x is None else str(x)


def one_line(text, limit: int) -> str:
    """``text`` on one line (its whitespace runs made single spaces), cut to ``limit``
    characters with "..." after a cut: a verdict's or a view's reason in a report."""
    flat = " ".join(str(text).split())
    return flat[:limit] + ("..." if len(flat) > limit else "")


def markdown_table(df: pd.DataFrame, floatfmt: str = ".3g") -> str:
    """A plain markdown table (no extra dependency)."""
    cols = [str(c) for c in df.columns]
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for row in df.itertuples(index=False):
        cells = []
        for v in row:
            if isinstance(v, float | np.floating):
                cells.append("" if np.isnan(v) else format(v, floatfmt))
            else:
                cells.append(str(v))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def plain_log_ticks(ax, axis: str = "y") -> None:
    """A log axis labelled in plain numbers at 1, 2 and 5 per decade (matplotlib labels
    the minor ticks as 4x10^0 where a decade is short: a review, h87)."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    a = ax.yaxis if axis == "y" else ax.xaxis
    lo, hi = sorted(ax.get_ylim() if axis == "y" else ax.get_xlim())
    decades = np.log10(hi / lo) if lo > 0 and hi > lo else 1.0
    # 1, 2, 5 per decade over a few decades; 1 per decade beyond (a review, h90: over ten
    # decades 1-2-5 drew no tick at all, over eight thirty labels)
    subs = (1.0, 2.0, 5.0) if decades <= 4.5 else (1.0,)
    a.set_major_locator(LogLocator(base=10.0, subs=subs, numticks=40))
    a.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    a.set_minor_formatter(NullFormatter())


#: the name of a ``testbed score`` run: ``score METHOD`` (its report, reproduce line and
#: trials' owner say a dataset's scores, not a study of a scene file)
SCORE_PREFIX = "score "


def scored_method(name: str) -> str | None:
    """The method a ``testbed score`` run's ``name`` scores, or None for a study's name."""
    return name.removeprefix(SCORE_PREFIX) if name.startswith(SCORE_PREFIX) else None


def reproduce_command(ctx: StudyContext) -> str:
    """The command that runs the study again to the same results (a review, h87: the reports
    did not say how they were made). Workers and a Dask scheduler are left out: the trials'
    seeds do not depend on them. A shipped scene by its name, so that a checkout of the
    commit reads its own copy (a review, h90: the absolute path named another tree's file);
    any other by its path, whose content the report's sha256 records."""
    import shlex

    path = Path(ctx.scene_path)
    method = scored_method(ctx.name)
    if method is not None:   # testbed score's (a review, h97: "testbed study 'score reglib'")
        return shlex.join(["testbed", "score", str(path)]
                          + ([] if method == "reglib" else ["--method", method])
                          + ["--out", "DIR"])
    try:
        shipped = path.resolve().parent == scenes_dir().resolve()
    except (OSError, RuntimeError, ValueError):
        shipped = False
    words = ["testbed", "study", ctx.name, "--scene", path.stem if shipped else str(path),
             "--seed", str(ctx.seed)] + (["--quick"] if ctx.quick else []) + ["--out", "DIR"]
    return shlex.join(words)


def file_sha256(path) -> str:
    """The sha256 of a file's bytes (``unreadable`` when it cannot be read)."""
    import hashlib

    try:
        return hashlib.sha256(Path(path).read_bytes()).hexdigest()
    except OSError:
        return "unreadable"


def library_versions() -> str:
    """Python's and the numerical libraries' versions (those whose upgrade changes a trial's
    result: :data:`studies.runner.CODE_LIBRARIES`), as ``name version`` pairs."""
    import platform

    from studies.runner import installed_versions

    return ", ".join([f"python {platform.python_version()}"]
                     + [f"{lib} {v}" if v is not None else f"{lib} (not installed)"
                        for lib, v in installed_versions().items()])


def finish_study(ctx: StudyContext, df: pd.DataFrame) -> None:
    """Write ``results.csv`` and ``report.md`` for a finished study."""
    check_results(df)
    df.to_csv(ctx.out / "results.csv", index=False)
    now = _dt.datetime.now(_dt.UTC).strftime("%Y-%m-%d %H:%M:%S UTC")
    commit = git_commit()
    resolved = json.dumps(ctx.scene.model_dump(mode="json"), indent=2)
    parts = [f"# Study `{ctx.name}`", ""]
    ws = getattr(ctx.scene, "workspace", None)
    if ws is not None and not ws.check and ctx.scene.scene.kind == "operating_room":
        parts += ["**The workspace was not checked** (`[workspace] check = false`): the "
                  "views and sweeps of this scene may not be physically possible.", ""]
    dataset = scored_method(ctx.name) is not None     # testbed score: a dataset's folder
    parts += [
        f"- {'dataset' if dataset else 'scene'}: `{ctx.scene_path}` ({ctx.scene.scene.name})",
        f"- seed: {ctx.seed}",
        f"- git commit: `{commit}`",
        f"- written: {now}; quick: {ctx.quick}; workers: {ctx.workers}"
        + (f"; Dask scheduler: {ctx.scheduler}" if ctx.scheduler else ""),
        f"- rows in results.csv: {len(df)}",
        (f"- dataset index (dataset.json) sha256: "
         f"`{file_sha256(Path(ctx.scene_path) / 'dataset.json')}`" if dataset else
         f"- scene file sha256: `{file_sha256(ctx.scene_path)}`"),
        f"- reproduce (at that commit, with these versions): `{reproduce_command(ctx)}`"
        + (" (the tree had uncommitted changes: the command reproduces these results only "
           "with them)" if commit.endswith("-dirty") else ""),
        f"- versions: {library_versions()}",
        "",
    ]
    sections = list(ctx.sections)
    failures = df.attrs.get("failures", {})
    if failures and not any("fail" in h.lower() for h, _ in sections):
        # a study that does not report its failed trials itself: each one's error, here
        sections.append(("Failed trials", "\n".join(f"- trial {k}: {v}"
                                                     for k, v in sorted(failures.items()))))
    for heading, body in sections:
        parts += [f"## {heading}", "", body, ""]
    if ctx.figures:
        parts += ["## Figures", ""]
        for fn, cap in ctx.figures:
            parts += [f"![{cap}]({fn})", "", f"*{cap}*", ""]
    parts += ["## Resolved scene", "", "```json", resolved, "```", ""]
    (ctx.out / "report.md").write_text("\n".join(parts))


#: share of a user mesh's length taken as each end's anatomy (:func:`region_centres`)
MESH_END_SHARE = 0.2


def region_centres(phantom) -> dict[str, np.ndarray]:
    """ct-frame centres of the anatomy a radiographer aims each region's views at: the
    femoral head and the trochanters; the condyles. A femur given as a mesh
    (``[phantom] mesh_path``) has no named landmarks: its ends stand for them, the centre of
    the bounding box of the vertices within :data:`MESH_END_SHARE` of its length from its
    top (proximal: the ct frame's z points up the femur) and from its bottom."""
    lm = phantom.landmarks
    need = ("head_center", "lesser_trochanter", "greater_trochanter", "medial_condyle",
            "lateral_condyle")
    if all(k in lm for k in need):
        prox = np.mean([lm["head_center"], lm["lesser_trochanter"],
                        lm["greater_trochanter"]], axis=0)
        dist = np.mean([lm["medial_condyle"], lm["lateral_condyle"]], axis=0)
        return {"proximal": prox, "distal": dist}
    v = np.asarray(phantom.femur.vertices, dtype=np.float64)
    lo, hi = v[:, 2].min(), v[:, 2].max()
    cut = MESH_END_SHARE * (hi - lo)

    def box_centre(sel):
        return 0.5 * (v[sel].min(axis=0) + v[sel].max(axis=0))

    return {"proximal": box_centre(v[:, 2] >= hi - cut),
            "distal": box_centre(v[:, 2] <= lo + cut)}


def report_scene_warnings(ctx: StudyContext, warnings, whose: str) -> None:
    """The report's "Warnings about the scene" section (none without warnings): what
    ``testbed run`` says of ``whose`` (e.g. "this scene at the study's seed"), which the
    figures after it carry."""
    if warnings:
        ctx.report("Warnings about the scene", f"What `testbed run` says of {whose}; the "
                   "figures below carry it:\n\n" + "\n".join(f"- {w}" for w in warnings))


def refuse_fixed_pin(scene, path, study: str) -> None:
    """ValueError naming the scene file and field when the scene locates a pin
    (``[registration] fixed_pin``) and the study registers free starts: the pin would be
    ignored without a word (a held-out review: table2, view-setups and error-budget
    registered an experiment1 scene as if it had no pin, and view-setups counted the result
    as a false refusal)."""
    if scene.registration.fixed_pin is not None:
        raise ValueError(
            f"{path}: [registration] fixed_pin = {scene.registration.fixed_pin!r}: {study} "
            "registers free starts, without a located pin; the experiment1 study and "
            "testbed run register about it")


def check_view_regions(scene, centres_robot=None, *, phantom=None) -> None:
    """``SceneError`` naming ``views[i].region`` when a view's isocentre lies nearer the
    other region's anatomy than its own: the studies that follow a view's region
    (re-aiming it at another femur, grouping views by region) would otherwise move or count
    it with the wrong end of the bone. ``centres_robot``: region -> (3,) mm in the robot
    frame (default: those of ``phantom``, else of the scene's femur, where its patient
    lies)."""
    from testbed.spec import SceneError

    if centres_robot is None:
        if phantom is None:
            from testbed.phantom import make_phantom

            phantom = make_phantom(scene.phantom)
        T = scene.patient.ct2robot()
        centres_robot = {k: T.apply(c) for k, c in region_centres(phantom).items()}
    for i, v in enumerate(scene.views):
        own = centres_robot.get(v.region)
        if own is None:
            continue
        iso = np.asarray(v.isocenter_mm, dtype=np.float64)
        d_own = float(np.linalg.norm(iso - own))
        for other, c in centres_robot.items():
            d_other = float(np.linalg.norm(iso - c))
            if other != v.region and d_other < d_own:
                raise SceneError(
                    f"views[{i}].region: view {v.name!r} is labelled {v.region!r} but its "
                    f"isocentre lies {d_other:.0f} mm from the {other} anatomy and {d_own:.0f} "
                    f"mm from the {v.region} one; label it {other!r} or move it")
