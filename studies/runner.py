"""The study runner: many independent trials, in parallel, resumable, trial by trial on disk.

A study is a list of :class:`Trial` (scene, seed, parameters) and a *trial function*
``trial_fn(trial) -> list[dict]`` that returns long-format rows (``metric``, ``value``,
``unit`` plus any parameter keys of its own). :func:`run_trials` runs them

- in-process (``workers=1``), on a process pool (``workers > 1``, ``concurrent.futures`` with
  the ``spawn`` or ``forkserver`` start method), or on a Dask cluster (``scheduler=`` an
  address ``tcp://HOST:PORT``, a ``dask.distributed.Client`` or a ``LocalCluster``);
- with a tqdm progress bar;
- writing every finished trial at once to the SQLite database ``out_dir/trials.sqlite``
  (WAL journal, one transaction per trial holding its status and all its rows), so that a
  study stopped by Ctrl-C, ``kill -9`` or a lost worker is resumed by calling
  :func:`run_trials` again with the same trials: trials already in the database are not run
  again, and the result is exactly the rows of an uninterrupted run.

Seeds come from the trial, never from the worker: :func:`make_trials` gives trial ``i`` the
child ``i`` of ``numpy.random.SeedSequence(study_seed).spawn(n)``, stored as its ``entropy``
and ``spawn_key`` so that :meth:`Trial.rng` rebuilds the same generator in any process. The
rows therefore do not depend on the number of workers or on the order trials finish in.

Failures. A trial whose function raises (any ``Exception``), returns malformed rows, or
whose worker process dies while running it alone, is stored with status ``failed``, its error
message and traceback, and does not stop the study. In the returned table it contributes one
row ``metric="failed"``, ``value=1.0``, ``unit=""`` (plus its parameters); the messages are
in ``df.attrs["failures"]`` and :func:`read_failures`. Failed trials are not rerun on resume
unless ``retry_failed=True``.

Database schema (``trials.sqlite``)::

    trials(key TEXT PRIMARY KEY,     -- hash of (index, scene, entropy, spawn_key, params)
           trial INTEGER,            -- the trial index
           scene TEXT, seed TEXT,    -- seed: JSON {"entropy": int, "spawn_key": [int, ...]}
           params TEXT,              -- JSON object of the trial's parameters
           status TEXT,              -- 'done' or 'failed'
           error TEXT, traceback TEXT,
           seconds REAL,             -- wall time of the trial function in its worker, s
           worker TEXT,              -- host:pid that ran it
           finished_at TEXT)         -- UTC ISO time the row was written
    rows(key TEXT, trial INTEGER, row INTEGER,   -- row: position in the trial's list
         metric TEXT, value REAL, unit TEXT,
         extra TEXT,                 -- JSON object of the row's own parameter keys
         PRIMARY KEY (key, row))

NaN values are stored as SQL NULL and read back as NaN; every other float round-trips
bitwise (SQLite REAL is an IEEE double).
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import datetime as _dt
import functools
import hashlib
import json
import math
import multiprocessing
import numbers
import os
import pickle
import socket
import sqlite3
import sys
import time
import traceback
import weakref
from collections.abc import Callable, Iterable, Mapping, Sequence
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pandas as pd

__all__ = [
    "DB_NAME",
    "FAILED_METRIC",
    "StudyDatabaseError",
    "Trial",
    "TrialResult",
    "make_trials",
    "read_failures",
    "read_results",
    "read_trials",
    "run_study_trials",
    "run_trials",
    "interrupt_of",
]

DB_NAME = "trials.sqlite"
FAILED_METRIC = "failed"
_ROW_CORE = ("metric", "value", "unit")
_RESERVED = ("trial", "metric", "value", "unit")


# --------------------------------------------------------------------------- trials
def _scalar(value, what: str):
    """A JSON-able scalar (str, int, float, bool, None) from ``value``, or ``ValueError``."""
    if isinstance(value, np.generic):
        value = value.item()
    if value is None or isinstance(value, str | bool | int | float):
        return value
    raise ValueError(f"{what}: expected a scalar (str, int, float, bool or None), "
                     f"got {type(value).__name__}")


@dataclass(frozen=True)
class Trial:
    """One trial of a study.

    Parameters
    ----------
    index : int
        Position of the trial in the study (0-based); the ``trial`` column of the results.
    scene : str
        Scene name or path (as :func:`testbed.scene.find_scene` takes it).
    entropy : int
        Entropy of the trial's ``numpy.random.SeedSequence``.
    spawn_key : tuple of int
        Its spawn key: ``SeedSequence(entropy, spawn_key=spawn_key)`` is the trial's seed.
    params : dict
        Scalar parameters (str, int, float, bool, None); each becomes a column of the results.
    fingerprint : str
        A digest of what the trial reads besides its parameters (the scene's content, a
        dataset's files, a method's source: :func:`fingerprint`), part of its ``key``: a
        trial stored from other contents under the same path is not taken for this one.
    """

    index: int
    scene: str
    entropy: int
    spawn_key: tuple[int, ...] = ()
    params: Mapping[str, Any] = field(default_factory=dict)
    fingerprint: str = ""

    def __post_init__(self):
        if isinstance(self.index, bool) or not isinstance(self.index, numbers.Integral) \
                or self.index < 0:
            raise ValueError(f"Trial.index: expected an int >= 0, got {self.index!r}")
        if not isinstance(self.scene, str | os.PathLike):
            raise ValueError(f"Trial.scene: expected a scene name or path, got {self.scene!r}")
        if not isinstance(self.entropy, numbers.Integral) or self.entropy < 0:
            raise ValueError(f"Trial.entropy: expected an int >= 0, got {self.entropy!r}")
        params = {}
        for k, v in dict(self.params).items():
            if not isinstance(k, str):
                raise ValueError(f"Trial {self.index}: parameter names must be str, got {k!r}")
            if k in _RESERVED:
                raise ValueError(f"Trial {self.index}: parameter {k!r} clashes with the "
                                 f"column of the same name; rename it")
            params[k] = _scalar(v, f"Trial {self.index}: parameter {k!r}")
        object.__setattr__(self, "index", int(self.index))
        object.__setattr__(self, "scene", str(self.scene))
        object.__setattr__(self, "entropy", int(self.entropy))
        object.__setattr__(self, "spawn_key", tuple(int(s) for s in self.spawn_key))
        object.__setattr__(self, "params", params)

    @classmethod
    def from_seed_sequence(cls, index: int, scene: str, seed: np.random.SeedSequence,
                           params: Mapping[str, Any] | None = None, fingerprint: str = ""
                           ) -> Trial:
        """A trial whose seed is ``seed`` (a child of ``SeedSequence(study_seed).spawn``)."""
        if seed.n_children_spawned:
            raise ValueError(f"Trial {index}: its SeedSequence has already spawned children; "
                             "pass a fresh child of SeedSequence(study_seed).spawn(n)")
        return cls(index, scene, int(seed.entropy), tuple(seed.spawn_key), dict(params or {}),
                   str(fingerprint))

    @property
    def seed_sequence(self) -> np.random.SeedSequence:
        """The trial's ``SeedSequence``, rebuilt from ``entropy`` and ``spawn_key``."""
        return np.random.SeedSequence(self.entropy, spawn_key=self.spawn_key)

    def rng(self) -> np.random.Generator:
        """A fresh ``numpy.random.Generator`` (PCG64) seeded by the trial: same in any worker."""
        return np.random.default_rng(self.seed_sequence)

    @property
    def key(self) -> str:
        """A stable identity (sha1 of index, scene, seed, params and fingerprint) used by the
        database; without a fingerprint, the key of the versions before it."""
        parts = [self.index, self.scene, self.entropy, list(self.spawn_key), self.params]
        if self.fingerprint:
            parts.append(self.fingerprint)
        blob = json.dumps(parts, sort_keys=True, allow_nan=True)
        return hashlib.sha1(blob.encode()).hexdigest()


def fingerprint(*, texts=(), files=()) -> str:
    """sha256 (hex) of ``texts`` (str) and the bytes of ``files`` (paths; a missing one
    counts by its name): what a trial reads that its parameters do not say."""
    h = hashlib.sha256()
    for t in texts:
        h.update(str(t).encode())
        h.update(b"\0")
    for f in files:
        h.update(str(f).encode())
        try:
            with open(f, "rb") as fh:
                for chunk in iter(lambda: fh.read(1 << 20), b""):
                    h.update(chunk)
        except OSError:
            h.update(b"missing")
    return h.hexdigest()


def make_trials(scene: str, study_seed: int, params: Sequence[Mapping[str, Any]], *,
                fingerprint: str = "") -> list[Trial]:
    """One trial per entry of ``params``; trial ``i`` gets child ``i`` of
    ``SeedSequence(study_seed).spawn(len(params))``.

    Parameters
    ----------
    scene : str
        Scene name or path shared by the trials.
    study_seed : int
        The study's seed (>= 0).
    params : sequence of dict
        The parameters of each trial (scalars).
    fingerprint : str
        :attr:`Trial.fingerprint` of every trial.
    """
    if isinstance(study_seed, bool) or not isinstance(study_seed, numbers.Integral) \
            or study_seed < 0:
        raise ValueError(f"make_trials: study_seed must be an int >= 0, got {study_seed!r}")
    children = np.random.SeedSequence(int(study_seed)).spawn(len(params))
    return [Trial.from_seed_sequence(i, scene, s, p, fingerprint)
            for i, (s, p) in enumerate(zip(children, params, strict=True))]


# --------------------------------------------------------------------------- one trial
@dataclass(frozen=True)
class TrialResult:
    """What a worker sends back: status ``done`` or ``failed``, rows, error, timing (s)."""

    key: str
    index: int
    status: Literal["done", "failed"]
    rows: tuple[dict, ...]
    error: str = ""
    traceback: str = ""
    seconds: float = float("nan")
    worker: str = ""


def _check_rows(rows, trial: Trial) -> list[dict]:
    """Validate the rows a trial function returned; ``ValueError`` naming the bad row/key."""
    if isinstance(rows, Mapping) or not isinstance(rows, Iterable):
        raise ValueError(f"trial {trial.index}: trial_fn must return a list of dicts, got "
                         f"{type(rows).__name__}")
    out = []
    for i, row in enumerate(rows):
        if not isinstance(row, Mapping):
            raise ValueError(f"trial {trial.index}, row {i}: expected a dict, got "
                             f"{type(row).__name__}")
        missing = [c for c in _ROW_CORE if c not in row]
        if missing:
            raise ValueError(f"trial {trial.index}, row {i}: missing keys {missing}")
        metric, unit, value = row["metric"], row["unit"], row["value"]
        if not isinstance(metric, str) or not metric:
            raise ValueError(f"trial {trial.index}, row {i}: 'metric' must be a non-empty str")
        if metric == FAILED_METRIC:
            raise ValueError(f"trial {trial.index}, row {i}: the metric name {FAILED_METRIC!r} "
                             "is reserved for failed trials")
        if not isinstance(unit, str):
            raise ValueError(f"trial {trial.index}, row {i}: 'unit' must be a str, got "
                             f"{type(unit).__name__}")
        if isinstance(value, np.generic):
            value = value.item()
        if isinstance(value, bool) or not isinstance(value, numbers.Real):
            raise ValueError(f"trial {trial.index}, row {i} ({metric}): 'value' must be a "
                             f"real number, got {type(value).__name__}")
        extra = {}
        for k, v in row.items():
            if k in _ROW_CORE:
                continue
            if k == "trial":
                raise ValueError(f"trial {trial.index}, row {i}: rows must not set 'trial' "
                                 "(the runner adds it)")
            v = _scalar(v, f"trial {trial.index}, row {i}: key {k!r}")
            if k in trial.params and trial.params[k] != v:
                raise ValueError(f"trial {trial.index}, row {i}: key {k!r} = {v!r} contradicts "
                                 f"the trial parameter {k!r} = {trial.params[k]!r}")
            if k not in trial.params:
                extra[k] = v
        out.append({"metric": metric, "value": float(value), "unit": unit, "extra": extra})
    return out


#: the longest error message and traceback a trial stores (characters): a review's method
#: raised a message of 5 MB, which went whole into the database and the report
MAX_ERROR_CHARS = 4000


def _describe(exc: BaseException) -> str:
    """``"Type: message"`` of a trial's exception, even when its ``__str__`` raises (that
    ended a review's command in an internal error)."""
    try:
        text = str(exc)
    except Exception as inner:  # noqa: BLE001 - whatever the user's __str__ raises
        text = f"(its message cannot be printed: {type(inner).__name__})"
    return f"{type(exc).__name__}: {text}"


def _format_traceback() -> str:
    try:
        return traceback.format_exc()
    except Exception:  # noqa: BLE001 - an exception that cannot even be formatted
        return ""


def _storable(text: str, *, tail: bool = False) -> str:
    """``text`` as the database can hold it: characters UTF-8 cannot encode (a lone
    surrogate, from text decoded with ``surrogateescape``) escaped, and at most
    :data:`MAX_ERROR_CHARS` characters, its start kept (``tail``: its end, a traceback's
    last frames) and the cut said so. A message SQLite could not encode ended a review's
    command with exit 2 and no results, on every rerun."""
    text = str(text).encode("utf-8", "backslashreplace").decode("utf-8")
    cut = len(text) - MAX_ERROR_CHARS
    if cut > 0:
        note = f" ... ({cut:,} characters cut) ... "
        text = note + text[cut:] if tail else text[:MAX_ERROR_CHARS] + note
    return text


#: the longest error message a report shows (characters)
REPORT_ERROR_CHARS = 300


def report_line(error: str) -> str:
    """A trial's error as one line of a markdown report: its lines joined by " / ", at
    most :data:`REPORT_ERROR_CHARS` characters (the whole stays in the database), backticks
    and ``<`` escaped with a backslash. A review's method raised a message with a markdown
    heading and an open code fence, which became a section of report.md and swallowed the
    sections after it."""
    lines = [ln.strip() for ln in str(error).strip().splitlines() if ln.strip()] or [""]
    text = " / ".join(lines)    # a scene error's field is on its second line
    if len(text) > REPORT_ERROR_CHARS:
        text = text[:REPORT_ERROR_CHARS] + " ... (the whole message: read_failures or " \
            "trials.sqlite)"
    # backslash escapes (CommonMark): "&lt;U32" read as an HTML entity in the raw file
    return text.replace("`", "\\`").replace("<", "\\<")


def interrupt_of(exc: BaseException) -> KeyboardInterrupt | None:
    """The KeyboardInterrupt (Ctrl-C, or SIGTERM as :class:`studies.cli.Terminated`) behind
    ``exc``, if any: one that arrives while a numba-compiled function runs surfaces as a
    SystemError ("returned a result with an exception set") whose context is the interrupt,
    an Exception that a trial's failure handler would otherwise take for the trial's own."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return exc
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return None


#: True in a pool worker that leads a process group of its own (:func:`_worker_start`): the
#: terminal's Ctrl-C does not reach it, so a KeyboardInterrupt there is the trial's own
_OWN_GROUP = False


def execute_trial(trial_fn: Callable[[Trial], list[dict]], trial: Trial, *,
                  interrupt_is_failure: bool | None = None) -> TrialResult:
    """Run one trial, catching its exceptions: the unit of work sent to a worker. An
    interrupt is no failure of the trial: it propagates (:func:`interrupt_of`), and the
    trial is run again when the study resumes; but in a pool worker of its own process
    group no Ctrl-C arrives, and a KeyboardInterrupt that a method raises is its failure
    (it ended a whole ``testbed score`` with exit 130, a review). ``interrupt_is_failure``:
    that choice made by the caller (True on a Dask worker, which no Ctrl-C of the study's
    terminal reaches); default: whether this is such a pool worker."""
    from studies.threads import freeze_worker, single_threaded_kernels

    single_threaded_kernels()       # workers parallelise by process
    who = f"{socket.gethostname()}:{os.getpid()}"
    t0 = time.perf_counter()
    try:
        rows = _check_rows(trial_fn(trial), trial)
    except BaseException as exc:  # a failing trial is recorded, not fatal (also a user's
        # method that calls sys.exit, or raises a BaseException of its own: a review's
        # ended the command with a traceback and no results)
        stop = interrupt_of(exc)
        own = _OWN_GROUP if interrupt_is_failure is None else interrupt_is_failure
        if stop is not None and not own:
            raise stop from None
        return TrialResult(trial.key, trial.index, "failed", (), error=_describe(exc),
                           traceback=_format_traceback(),
                           seconds=time.perf_counter() - t0, worker=who)
    result = TrialResult(trial.key, trial.index, "done", tuple(rows),
                         seconds=time.perf_counter() - t0, worker=who)
    freeze_worker()                 # after a worker's first trial (studies/threads.py)
    return result


# --------------------------------------------------------------------------- database
_SCHEMA = """
CREATE TABLE IF NOT EXISTS trials (
    key TEXT PRIMARY KEY, trial INTEGER NOT NULL, scene TEXT, seed TEXT, params TEXT,
    status TEXT NOT NULL, error TEXT, traceback TEXT, seconds REAL, worker TEXT,
    finished_at TEXT);
CREATE TABLE IF NOT EXISTS rows (
    key TEXT NOT NULL, trial INTEGER NOT NULL, row INTEGER NOT NULL, metric TEXT NOT NULL,
    value REAL, unit TEXT NOT NULL, extra TEXT NOT NULL, PRIMARY KEY (key, row));
CREATE INDEX IF NOT EXISTS rows_trial ON rows (trial, row);
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT);
"""


def stored_study(out_dir) -> str | None:
    """The study whose trials ``out_dir/trials.sqlite`` holds (``run_trials(study=...)``),
    or None (no database, an older one, or one that cannot be read: :func:`run_trials`
    reports that). Read before any work, it tells a study interrupted before its report
    from a free folder."""
    db = Path(out_dir) / DB_NAME
    if not db.is_file():
        return None
    try:
        con = sqlite3.connect(f"{db.resolve().as_uri()}?mode=ro", uri=True, timeout=10.0)
        try:
            row = con.execute("SELECT value FROM meta WHERE key = 'study'").fetchone()
        finally:
            con.close()
    except sqlite3.DatabaseError:
        return None
    return None if row is None else str(row[0])


def owner_conflict(stored: str | None, want: str) -> bool:
    """Whether a folder whose database names ``stored`` as its owner (None: no owner yet)
    refuses the trials of ``want``: another owner, unless a bare legacy name
    (:func:`legacy_owner`)."""
    return stored is not None and stored != want and not legacy_owner(stored, want)


def legacy_owner(stored: str, want: str) -> bool:
    """Whether ``stored``, the owner a study folder's database names, is the bare study name
    that studies recorded before they named their scene and seed too (``fig9`` for ``fig9 of
    /path/scene.toml, seed ...``): such a folder is taken by the first run of that study,
    which then owns it (its trials are reused where their keys agree: the same scene typed
    as an absolute path, or a named scene)."""
    return " " not in stored and want.startswith(stored + " of ")


def _claim(con: sqlite3.Connection, db_path: Path, study: str) -> None:
    """Record ``study`` as the owner of the database, or refuse one of another study."""
    row = con.execute("SELECT value FROM meta WHERE key = 'study'").fetchone()
    if owner_conflict(None if row is None else row[0], study):
        raise ValueError(f"{db_path}: holds the trials of {row[0]!r}, not of {study!r}; "
                         "give another folder, or that study's command to resume it")
    if row is None:
        con.execute("INSERT OR IGNORE INTO meta VALUES ('study', ?)", (study,))
    elif row[0] != study:   # a folder of before, owned by the bare study name: now this run's
        con.execute("UPDATE meta SET value = ? WHERE key = 'study'", (study,))


class StudyDatabaseError(ValueError):
    """``trials.sqlite`` cannot be read: the message says what to do."""


def _connect(db_path: Path) -> sqlite3.Connection:
    try:
        con = sqlite3.connect(db_path, timeout=60.0, isolation_level=None)
        con.execute("PRAGMA journal_mode=WAL")
        # NORMAL is durable against a killed process (not against power loss) in WAL mode.
        con.execute("PRAGMA synchronous=NORMAL")
        con.executescript(_SCHEMA)
        con.execute("SELECT key, trial, status FROM trials LIMIT 1").fetchall()
        con.execute("SELECT key, row, metric FROM rows LIMIT 1").fetchall()
    except sqlite3.DatabaseError as exc:
        raise StudyDatabaseError(
            f"{db_path}: not a readable study database ({exc}); move it away (e.g. "
            f"mv {db_path} {db_path}.bad) to start the study again, or use another --out"
        ) from None
    return con


def _done_keys(con: sqlite3.Connection, *, retry_failed: bool) -> set[str]:
    if retry_failed:
        q = "SELECT key FROM trials WHERE status = 'done'"
    else:
        q = "SELECT key FROM trials"
    return {k for (k,) in con.execute(q)}


def _stale_count(con: sqlite3.Connection, todo: Sequence[Trial]) -> int:
    """How many of ``todo`` have a stored trial of the same index and parameters under
    another key (their fingerprint changed: other code, scene or files)."""
    if not todo:
        return 0
    stored: dict[tuple[int, str], set[str]] = {}
    for k, i, p in con.execute("SELECT key, trial, params FROM trials"):
        stored.setdefault((int(i), p), set()).add(k)
    return sum(bool(stored.get((t.index, json.dumps(t.params)), set()) - {t.key})
               for t in todo)


def _store(con: sqlite3.Connection, trial: Trial, res: TrialResult) -> None:
    """Write one trial (status and all its rows) in one transaction."""
    now = _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")
    seed = json.dumps({"entropy": trial.entropy, "spawn_key": list(trial.spawn_key)})
    con.execute("BEGIN IMMEDIATE")
    try:
        con.execute("DELETE FROM rows WHERE key = ?", (trial.key,))
        con.execute(
            "INSERT OR REPLACE INTO trials VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
            (trial.key, trial.index, trial.scene, seed, json.dumps(trial.params),
             res.status, _storable(res.error), _storable(res.traceback, tail=True), res.seconds,
             res.worker, now))
        con.executemany(
            "INSERT INTO rows VALUES (?, ?, ?, ?, ?, ?, ?)",
            [(trial.key, trial.index, i, r["metric"],
              None if math.isnan(r["value"]) else r["value"], r["unit"],
              json.dumps(r["extra"])) for i, r in enumerate(res.rows)])
        con.execute("COMMIT")
    except BaseException:
        con.execute("ROLLBACK")
        raise


def read_trials(out_dir) -> pd.DataFrame:
    """The ``trials`` table of ``out_dir/trials.sqlite`` (one row per stored trial)."""
    db = Path(out_dir) / DB_NAME
    if not db.exists():
        raise FileNotFoundError(f"no study database {db}")
    with sqlite3.connect(db) as con:
        return pd.read_sql_query("SELECT * FROM trials ORDER BY trial", con)


def read_failures(out_dir) -> pd.DataFrame:
    """Failed trials: columns ``trial``, ``error``, ``traceback``, ``key`` (by trial)."""
    t = read_trials(out_dir)
    return t.loc[t.status == "failed", ["trial", "error", "traceback", "key"]].reset_index(
        drop=True)


def read_results(out_dir, trials: Sequence[Trial] | None = None) -> pd.DataFrame:
    """The long-format results stored in ``out_dir``, ordered by trial index and row index.

    Parameters
    ----------
    out_dir : path
        The study folder holding ``trials.sqlite``.
    trials : sequence of Trial, optional
        Keep only these trials (by key). All stored trials if None.

    Returns
    -------
    DataFrame with columns ``trial``, ``metric``, ``value``, ``unit``, then the parameter
    columns in order of first appearance (trial parameters, then the rows' own keys). A
    failed trial gives one row ``metric="failed"``, ``value=1.0``.
    ``df.attrs["failures"]`` is a dict trial index -> error message of the failed trials
    as a report shows it (:func:`report_line`; the whole message is in :func:`read_failures`)
    (plain values, so that ``pd.concat`` of results keeps working).
    """
    db = Path(out_dir) / DB_NAME
    if not db.exists():
        raise FileNotFoundError(f"no study database {db}")
    con = sqlite3.connect(db)
    try:
        tr = con.execute(
            "SELECT key, trial, params, status, error FROM trials ORDER BY trial").fetchall()
        rows_by_key: dict[str, list] = {}
        for key, _i, row, metric, value, unit, extra in con.execute(
                "SELECT * FROM rows ORDER BY trial, row"):
            rows_by_key.setdefault(key, []).append((row, metric, value, unit, extra))
    finally:
        con.close()
    wanted = None if trials is None else {t.key for t in trials}
    records, failures = [], {}
    for key, index, params_json, status, error in tr:
        if wanted is not None and key not in wanted:
            continue
        params = json.loads(params_json)
        if status == "failed":
            failures[index] = report_line(error)
            records.append({"trial": index, "metric": FAILED_METRIC, "value": 1.0, "unit": "",
                            **params})
            continue
        for _row, metric, value, unit, extra in rows_by_key.get(key, []):
            records.append({"trial": index, "metric": metric,
                            "value": float("nan") if value is None else value, "unit": unit,
                            **params, **json.loads(extra)})
    df = pd.DataFrame.from_records(records, columns=None if records else list(_RESERVED))
    df = df[list(_RESERVED) + [c for c in df.columns if c not in _RESERVED]]
    df["value"] = df["value"].astype(np.float64)
    df.attrs["failures"] = failures
    return df


# --------------------------------------------------------------------------- back-ends
def _progress(total: int, initial: int, enabled: bool):
    from tqdm.auto import tqdm

    return tqdm(total=total, initial=initial, disable=not enabled, unit="trial",
                dynamic_ncols=True, desc="trials")


def _run_local(trial_fn, todo, record) -> None:
    for trial in todo:
        record(trial, execute_trial(trial_fn, trial))


def _lost(trial: Trial, why: str) -> TrialResult:
    return TrialResult(trial.key, trial.index, "failed", (),
                       error=f"WorkerLost: the worker process died while running this trial "
                             f"alone ({why})")


def _timed_out(trial: Trial, timeout_s: float, started: bool = True) -> TrialResult:
    if started:
        error = (f"TimedOut: the trial still ran after {timeout_s:g} s (the per-trial time "
                 "limit) and its worker process was stopped")
    else:
        error = (f"TimedOut: no worker had started the trial {timeout_s + START_GRACE_S:g} s "
                 f"after it was handed over (the per-trial time limit, {timeout_s:g} s, "
                 f"plus {START_GRACE_S:g} s for a worker's start and imports) and the "
                 "workers were stopped")
    return TrialResult(trial.key, trial.index, "failed", (), error=error,
                       seconds=float(timeout_s))


def _kill_workers(ex: cf.ProcessPoolExecutor) -> None:
    """End the pool's worker processes at once (a trial past its time limit may be stuck in
    compiled code, where no signal reaches Python), each with the processes its trial
    started (its process group, :func:`_worker_start`); the pool is broken afterwards.
    Python 3.11's executor has no public call for it (3.14 adds ``kill_workers``). The
    caller shuts the pool down, without waiting."""
    import signal

    _signal_groups(ex, signal.SIGKILL)
    for proc in list((getattr(ex, "_processes", None) or {}).values()):
        try:
            proc.kill()     # a worker not (yet) leading a group of its own
        except (OSError, ValueError, AttributeError):  # gone already, or closed
            pass


def _signal_groups(ex: cf.ProcessPoolExecutor, sig) -> None:
    """Send ``sig`` to the process group of each live worker of pool ``ex``: the worker and
    what its trial started. Only while the worker lives (a reaped worker's pid may be
    another's), and no group of that id exists unless the worker made it."""
    if not hasattr(os, "killpg"):
        return
    for proc in list((getattr(ex, "_processes", None) or {}).values()):
        pid = getattr(proc, "pid", None)
        if pid and getattr(proc, "exitcode", 0) is None:
            try:
                os.killpg(pid, sig)
            except (OSError, ValueError):   # not yet its own group, or gone
                pass


#: seconds to wait, once a worker died, for the pool to fail the trials still in flight
POOL_SETTLE_S = 30.0
#: seconds between a pool worker's checks that the study's process still lives
PARENT_POLL_S = 1.0
#: longest wait of the study's main thread for its workers, so that a signal's Python
#: handler (Ctrl-Z, SIGCONT, Ctrl-C) runs within it whichever thread received the signal
SIGNAL_POLL_S = 0.25
#: seconds a pool worker may take to start a trial handed to it (its process's start, the
#: imports its first trial's unpickling makes) before a per-trial time limit counts anyway
START_GRACE_S = 120.0


def _process_alive(pid: int) -> bool:
    """Whether process ``pid`` runs: not gone, not a zombie (a killed process stays one
    until its parent reaps it, and ``os.kill(pid, 0)`` still succeeds on it)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] not in ("Z", "X")
    except FileNotFoundError:
        return False
    except (OSError, IndexError):  # no /proc: the signal test
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return False
        except PermissionError:
            return True
        return True


def _no_tqdm_process_lock() -> None:
    """tqdm's bars (even disabled ones) share a lock between processes, a semaphore that
    each worker made at its first bar; a worker killed (a time limit, Ctrl-C) could not
    release it, and the semaphore tracker warned of 'leaked semaphore objects' after every
    interrupted study. A worker draws no bar on the terminal: the lock of its threads is
    enough (tqdm leaves the process lock out when it is None)."""
    try:
        from tqdm.std import TqdmDefaultWriteLock
    except ImportError:
        return
    if not hasattr(TqdmDefaultWriteLock, "mp_lock"):
        TqdmDefaultWriteLock.mp_lock = None


#: in a pool worker: the queue on which it tells the study's process when it starts a trial
_STARTS = None


def _pool_trial(trial_fn, trial: Trial) -> TrialResult:
    """:func:`execute_trial` in a pool worker, first telling the pool's owner the moment it
    starts (``trial.key``, ``time.monotonic()``): a per-trial time limit counts from there.
    It counted from the hand-over, which included the worker's start and the imports its
    first trial's unpickling makes: under load a trial of 0.3 s passed a limit of 4 s."""
    if _STARTS is not None:
        _STARTS.put((trial.key, time.monotonic()))
    return execute_trial(trial_fn, trial)


def _worker_start(parent_pid: int, starts=None) -> None:
    """Pool worker initializer: a process group of its own (below), pybullet imported
    without its banner (a study's workers each printed it on stderr), and a daemon thread
    that ends this worker when the study's process ``parent_pid`` is gone. A study killed
    by SIGKILL, the OOM killer or a batch system's hard limit cannot stop its pool, and the
    workers (each holding both ends of its call queue, so never reading EOF) lived on idle,
    0.8 GB each; the study resumes from its database, so nothing they held is lost."""
    import signal
    import threading

    from studies.threads import quiet_pybullet

    # A process group of its own, so that a kill reaches the processes a trial starts (a
    # method's helper programs outlived its worker when a time limit or Ctrl-C ended it, a
    # review). The terminal's Ctrl-C then reaches the study's process alone, which kills
    # its workers (_run_pool); a worker started and interrupted printed its traceback.
    global _OWN_GROUP, _STARTS
    _STARTS = starts
    try:
        os.setpgid(0, 0)
        _OWN_GROUP = True
    except (OSError, AttributeError):   # a session leader, or no process groups (Windows):
        pass                            # the worker alone is killed
    # ...a group in the terminal's background: a write to the terminal under `stty tostop`
    # (a method that prints) would stop the worker, and the study with it; ignored, the
    # write goes through, and a read of the terminal fails instead of stopping
    for name in ("SIGTTOU", "SIGTTIN"):
        if hasattr(signal, name):
            signal.signal(getattr(signal, name), signal.SIG_IGN)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    quiet_pybullet()
    _no_tqdm_process_lock()

    def watch():
        while _process_alive(parent_pid):
            time.sleep(PARENT_POLL_S)
        if hasattr(os, "killpg") and os.getpgid(0) == os.getpid():  # its group: what its
            os.killpg(0, signal.SIGKILL)                             # trial started, and it
        os._exit(70)

    threading.Thread(target=watch, name="end-with-study", daemon=True).start()


def _collect(done, running: dict, record, suspects: list) -> bool:
    """Record the finished futures ``done`` (removed from ``running``); those the pool's
    breaking failed become ``suspects``. True if any did."""
    broken = False
    for fut in done:
        t = running.pop(fut)
        try:
            res = fut.result()
        except BrokenProcessPool:
            suspects.append(t)
            broken = True
            continue
        record(t, res)
    return broken


def _run_pool(trial_fn, todo, record, *, workers: int, mp_context: str,
              retries: int = 2, timeout_s: float | None = None) -> None:
    """Process pool with at most ``workers`` trials in flight, so that when a worker dies
    (BrokenProcessPool) the suspects are known: they are rerun one at a time in a fresh
    one-worker pool (``retries`` more times if the worker dies again), and a trial that
    kills its worker every time even alone is recorded as failed. A trial still running
    ``timeout_s`` after its worker started it is recorded as failed and the pool's
    workers are killed; the other trials then in flight go back to the queue (not suspects:
    they did nothing wrong) and a new pool takes over."""
    ctx = multiprocessing.get_context(mp_context)
    if mp_context == "forkserver":
        # Workers fork from one server that has imported these once (no effect once the
        # server of this process runs); cheap worker (re)starts.
        mods = ["studies._forkserver", "studies._quiet", "studies.runner"]
        if getattr(trial_fn, "__module__", "__main__") not in ("__main__", "__mp_main__"):
            mods.append(trial_fn.__module__)
        ctx.set_forkserver_preload(mods)
    with _job_control():
        _pool_loop(trial_fn, todo, record, workers=workers, ctx=ctx, retries=retries,
                   timeout_s=timeout_s)


#: the pools of this process (weakly held): what Ctrl-Z stops and SIGCONT resumes
_POOLS: weakref.WeakSet = weakref.WeakSet()


def _new_pool(workers: int, ctx) -> cf.ProcessPoolExecutor:
    """A pool whose workers report each trial's start on ``ex.trial_starts`` (a queue of
    its own: a worker killed while writing to it could hold its lock, and a killed pool is
    never used again)."""
    starts = ctx.SimpleQueue()
    ex = cf.ProcessPoolExecutor(workers, mp_context=ctx, initializer=_worker_start,
                                initargs=(os.getpid(), starts))
    ex.trial_starts = starts
    _POOLS.add(ex)
    return ex


class _Deadlines:
    """When each trial in flight must be done: ``timeout_s`` after its worker started it
    (:func:`_pool_trial`), or ``timeout_s + START_GRACE_S`` after the hand-over while no
    worker has reported its start."""

    def __init__(self, ex: cf.ProcessPoolExecutor, timeout_s: float | None):
        self.ex, self.timeout_s = ex, timeout_s
        self.at: dict[str, float] = {}
        self.started: set[str] = set()

    def handed(self, trial: Trial) -> None:
        if self.timeout_s is not None:
            self.at[trial.key] = time.monotonic() + self.timeout_s + START_GRACE_S

    def update(self) -> None:
        """Read the starts the workers reported (always: an unread queue would fill and
        block them); ``time.monotonic`` is one clock for every process of the machine."""
        q = self.ex.trial_starts
        while not q.empty():
            key, t0 = q.get()
            if key in self.at and self.timeout_s is not None:
                self.at[key] = min(t0, time.monotonic()) + self.timeout_s
                self.started.add(key)

    def wait_s(self, trials) -> float:
        """Seconds until the first of ``trials`` is due, in slices of SIGNAL_POLL_S."""
        due = [self.at[t.key] for t in trials if t.key in self.at]
        if not due:
            return SIGNAL_POLL_S
        return min(SIGNAL_POLL_S, max(0.0, min(due) - time.monotonic()))

    def late(self, trial: Trial, now: float) -> bool:
        return trial.key in self.at and self.at[trial.key] <= now

    def timed_out(self, trial: Trial) -> TrialResult:
        return _timed_out(trial, self.timeout_s, trial.key in self.started)


def _signal_workers(sig) -> None:
    """Send ``sig`` to the process group of every live worker of this process's pools."""
    for ex in list(_POOLS):
        _signal_groups(ex, sig)


@contextlib.contextmanager
def _job_control():
    """While a pool runs: Ctrl-Z (SIGTSTP) stops the workers with the study, and SIGCONT
    (``fg``, ``bg``) resumes them. The workers lead process groups of their own, so the
    terminal's stop reached the study's process alone and its workers went on computing (a
    review). Only where the default stop applies (the main thread, SIGTSTP not ignored)."""
    import signal
    import threading

    if (not hasattr(signal, "SIGTSTP") or not hasattr(os, "killpg")
            or threading.current_thread() is not threading.main_thread()
            or signal.getsignal(signal.SIGTSTP) is not signal.SIG_DFL):
        yield
        return

    def on_stop(signum, frame):
        _signal_workers(signal.SIGSTOP)
        os.kill(os.getpid(), signal.SIGSTOP)     # as the default action; goes on at SIGCONT

    def on_continue(signum, frame):
        _signal_workers(signal.SIGCONT)

    before = signal.signal(signal.SIGTSTP, on_stop), signal.signal(signal.SIGCONT, on_continue)
    try:
        yield
    finally:
        signal.signal(signal.SIGTSTP, before[0])
        signal.signal(signal.SIGCONT, before[1])


def _result_in_slices(fut: cf.Future, trial: Trial, deadlines: _Deadlines):
    """``fut.result()``, waited for in slices of :data:`SIGNAL_POLL_S` (signal handlers run
    between them); ``cf.TimeoutError`` once ``trial`` is past its deadline."""
    while True:
        deadlines.update()
        try:
            return fut.result(timeout=deadlines.wait_s([trial]))
        except cf.TimeoutError:
            if deadlines.late(trial, time.monotonic()):
                raise


def _pool_loop(trial_fn, todo, record, *, workers: int, ctx, retries: int,
               timeout_s: float | None) -> None:
    """:func:`_run_pool`'s loop."""
    queue = list(reversed(todo))  # pop() from the end = in trial order
    suspects: list[Trial] = []
    while queue or suspects:
        if suspects:
            trial = suspects.pop(0)
            for attempt in range(retries + 1):
                ex = _new_pool(1, ctx)
                deadlines = _Deadlines(ex, timeout_s)
                killed = False
                try:
                    fut = ex.submit(_pool_trial, trial_fn, trial)
                    deadlines.handed(trial)
                    res = _result_in_slices(fut, trial, deadlines)
                    break
                except BrokenProcessPool as exc:
                    res = _lost(trial, f"{str(exc) or type(exc).__name__}; "
                                f"{attempt + 1} attempt(s) alone")
                except BaseException as exc:  # past its time limit, or Ctrl-C (a worker
                    _kill_workers(ex)            # that ignores it would hold the command)
                    killed = True
                    if not isinstance(exc, cf.TimeoutError):
                        raise
                    res = deadlines.timed_out(trial)
                    break
                finally:
                    ex.shutdown(wait=not killed, cancel_futures=True)
                    ex.trial_starts.close()
            record(trial, res)
            continue
        ex = _new_pool(workers, ctx)
        running: dict[cf.Future, Trial] = {}
        deadlines = _Deadlines(ex, timeout_s)
        killed = False
        try:
            while queue or running:
                broken = False
                while queue and len(running) < workers:
                    t = queue.pop()
                    try:
                        fut = ex.submit(_pool_trial, trial_fn, t)
                    except BrokenProcessPool:  # a worker died since the last wait
                        queue.append(t)  # never started: back in line, not a suspect
                        broken = True
                        break
                    running[fut] = t
                    deadlines.handed(t)
                if not broken:
                    deadlines.update()
                    # in slices: a signal the kernel hands to another of this process's
                    # threads runs its Python handler only when the main thread wakes, and
                    # a wait without end on stopped workers never did (SIGCONT after Ctrl-Z
                    # left them stopped, a CI run)
                    done, _ = cf.wait(running, timeout=deadlines.wait_s(running.values()),
                                      return_when=cf.FIRST_COMPLETED)
                    broken = _collect(done, running, record, suspects)
                    deadlines.update()
                    now = time.monotonic()
                    late = [f for f, t in running.items() if deadlines.late(t, now)]
                    if late and not broken:
                        _kill_workers(ex)
                        killed = True
                        for f in late:
                            t = running.pop(f)
                            record(t, deadlines.timed_out(t))
                        # the others in flight start again in the next pool, in trial order
                        queue.extend(sorted(running.values(), key=lambda tr: -tr.index))
                        running.clear()
                        break
                if broken:
                    # a broken pool fails every trial still in flight at once; those that
                    # finished before it broke keep their results, the others are suspects
                    done, _ = cf.wait(running, timeout=POOL_SETTLE_S)
                    _collect(done, running, record, suspects)
                    suspects.extend(running.values())
                    suspects.sort(key=lambda tr: tr.index)
                    running.clear()
                    break
        except BaseException:
            # Ctrl-C (or an error of our own): a method stuck in code that ignores SIGINT
            # kept its worker, and the command waited for it at exit for ever (a review)
            _kill_workers(ex)
            killed = True
            raise
        finally:
            for fut in running:
                fut.cancel()
            ex.shutdown(wait=not (running or killed), cancel_futures=True)
            ex.trial_starts.close()


#: error types of a lost worker or connection (Dask), not of the trial itself: retried
LOST_WORKER_ERRORS = ("KilledWorker", "CommClosedError", "StreamClosedError",
                      "FutureCancelledError", "CancelledError")
#: seconds to wait for a Dask scheduler before giving up
SCHEDULER_TIMEOUT_S = 10.0


def _client(address: str):
    """A Dask client for ``address``, or ValueError within SCHEDULER_TIMEOUT_S."""
    import socket
    from urllib.parse import urlparse

    from distributed import Client

    try:    # a malformed address raises in urlparse ("Invalid IPv6 URL") or in .port
        u = urlparse(address)
        host, port = u.hostname, u.port
    except ValueError:
        host = port = None
    if host is None or not port or u.scheme not in ("tcp", "tls"):
        raise ValueError(f"--scheduler {address!r}: expected an address tcp://HOST:PORT")
    try:
        with socket.create_connection((host, port), timeout=SCHEDULER_TIMEOUT_S):
            pass
    except OSError as exc:
        raise ValueError(f"--scheduler {address}: no scheduler answers there "
                         f"({exc.strerror or exc}); start one (dask scheduler) or check the "
                         "address") from None
    try:
        return Client(address, timeout=SCHEDULER_TIMEOUT_S)
    except (OSError, TimeoutError) as exc:
        raise ValueError(f"--scheduler {address}: cannot connect within "
                         f"{SCHEDULER_TIMEOUT_S:g} s ({exc})") from None


def _run_dask(trial_fn, todo, record, *, scheduler, retries: int = 2) -> None:
    try:
        from distributed import Client, as_completed
    except ImportError as exc:  # pragma: no cover - depends on the installation
        raise ImportError("run_trials(scheduler=...) needs dask.distributed: "
                          "pip install 'dask[distributed]'") from exc
    own = False
    if isinstance(scheduler, Client):
        client = scheduler
    elif isinstance(scheduler, str):
        client, own = _client(scheduler), True
    elif hasattr(scheduler, "scheduler_address"):
        client, own = Client(scheduler), True
    else:
        raise ValueError("scheduler: expected an address 'tcp://HOST:PORT', a "
                         f"dask.distributed.Client or a cluster, got {type(scheduler).__name__}")
    futures = {}
    attempts: dict[str, int] = {}
    try:
        for t in todo:
            fut = client.submit(execute_trial, trial_fn, t, pure=False,
                                interrupt_is_failure=True)
            futures[fut] = t
        pending = as_completed(list(futures))
        for fut in pending:
            t = futures.pop(fut)
            try:
                res = fut.result()
            except Exception as exc:  # e.g. KilledWorker: the worker, not the trial
                lost = type(exc).__name__ in LOST_WORKER_ERRORS
                attempts[t.key] = attempts.get(t.key, 0) + 1
                if lost and attempts[t.key] <= retries:
                    again = client.submit(execute_trial, trial_fn, t, pure=False,
                                          key=f"{t.key}-retry{attempts[t.key]}",
                                          interrupt_is_failure=True)
                    futures[again] = t
                    pending.add(again)
                    continue
                why = (f" (after {attempts[t.key]} attempts: a lost worker each time)"
                       if lost else "")
                res = TrialResult(t.key, t.index, "failed", (),
                                  error=f"{type(exc).__name__}: {exc}{why}",
                                  traceback=traceback.format_exc())
            record(t, res)
    finally:
        if futures:
            client.cancel(list(futures))
        if own:
            client.close()


# --------------------------------------------------------------------------- the runner
def run_trials(
    trial_fn: Callable[[Trial], list[dict]],
    trials: Sequence[Trial],
    *,
    out_dir,
    workers: int = 1,
    scheduler=None,
    progress: bool = True,
    resume: bool = True,
    retry_failed: bool = False,
    mp_context: Literal["spawn", "forkserver"] | None = None,
    retries: int = 2,
    isolate: bool = False,
    timeout_s: float | None = None,
    study: str | None = None,
) -> pd.DataFrame:
    """Run ``trials`` with ``trial_fn``, storing each result as it finishes; return all rows.

    Parameters
    ----------
    trial_fn : callable
        A top-level (picklable) function ``trial_fn(trial) -> list[dict]``; each dict has
        ``metric`` (str), ``value`` (real), ``unit`` (str) and optionally scalar parameter
        keys of its own (e.g. ``pin``). It must draw every random number from
        ``trial.rng()`` (or ``trial.seed_sequence``).
    trials : sequence of Trial
        Distinct indices; see :func:`make_trials`.
    out_dir : path
        Folder of the study; the database is ``out_dir/trials.sqlite`` (created if needed).
    workers : int
        1: run in this process (unless ``isolate``). More: a process pool of that many
        workers. Ignored when ``scheduler`` is given.
    isolate : bool
        Run one worker in a process of its own too, so that a trial which ends its process
        (``os._exit``, a crash in compiled code) is recorded as failed, as in a pool, where
        in this process it ended the command with no results (code that is not the
        project's own: ``testbed score --method``).
    timeout_s : float, optional
        A trial still running this many seconds after a worker took it is recorded as
        failed (``TimedOut``) and its worker killed; the study goes on. Trials then run in
        worker processes even with ``workers=1`` (a trial in this process cannot be
        stopped). Not with ``scheduler``.
    study : str, optional
        The study's name, recorded in the database: a database of another study's trials is
        refused (``ValueError``) instead of mixed with them (a study interrupted before its
        report left a folder another study took, a review).
    scheduler : str, dask.distributed.Client or cluster, optional
        Run on Dask: an address ``tcp://HOST:PORT`` (a client is opened and closed here), a
        ``Client`` (used as is), or a cluster such as ``LocalCluster``.
    progress : bool
        Show a tqdm progress bar.
    resume : bool
        True: trials already stored (same key) are not run again. False: the database is
        emptied first and every trial runs.
    retry_failed : bool
        With ``resume``, run again the trials stored as failed.
    retries : int
        How many more times a trial whose worker was lost (a dead pool process; Dask's
        KilledWorker or a closed connection) is run before it is recorded as failed.
    mp_context : {"spawn", "forkserver"}, optional
        Start method of the process pool; default ``forkserver`` where the platform has it
        (workers fork from one server process that imported ``studies.runner`` and the trial
        function's module once, so (re)starting workers is cheap), else ``spawn``.

    Returns
    -------
    DataFrame
        :func:`read_results` for ``trials``: columns ``trial``, ``metric``, ``value``,
        ``unit`` + parameter columns, sorted by trial index and row index; the same whatever
        the number of workers. ``df.attrs`` holds ``failures`` (dict trial index ->
        error message), ``executed`` (trials run by this call) and ``skipped`` (found stored).
    """
    trials = list(trials)
    for t in trials:
        if not isinstance(t, Trial):
            raise ValueError(f"trials: expected Trial objects, got {type(t).__name__}")
    seen: dict[int, Trial] = {}
    for t in trials:
        if t.index in seen:
            raise ValueError(f"trials: index {t.index} is used twice")
        seen[t.index] = t
    if not callable(trial_fn):
        raise ValueError("trial_fn: expected a callable trial_fn(trial) -> list[dict]")
    if isinstance(workers, bool) or not isinstance(workers, numbers.Integral) or workers < 1:
        raise ValueError(f"workers: expected an int >= 1, got {workers!r}")
    if isinstance(retries, bool) or not isinstance(retries, numbers.Integral) or retries < 0:
        raise ValueError(f"retries: expected an int >= 0, got {retries!r}")
    if mp_context is None:
        methods = multiprocessing.get_all_start_methods()
        mp_context = "forkserver" if "forkserver" in methods else "spawn"
    if mp_context not in ("spawn", "forkserver"):
        raise ValueError(f"mp_context: expected 'spawn' or 'forkserver', got {mp_context!r}")

    if timeout_s is not None:
        if (isinstance(timeout_s, bool) or not isinstance(timeout_s, numbers.Real)
                or not math.isfinite(timeout_s) or timeout_s <= 0):
            raise ValueError(f"timeout_s: expected a number of seconds > 0, got {timeout_s!r}")
        if scheduler is not None:
            raise ValueError("timeout_s: a per-trial time limit needs local workers; with a "
                             "Dask scheduler set one on the cluster instead")
        timeout_s = float(timeout_s)
    pooled = workers > 1 or bool(isolate) or timeout_s is not None
    if scheduler is None and pooled:
        try:
            pickle.dumps(trial_fn)
        except Exception as exc:  # PicklingError, AttributeError, TypeError...
            raise ValueError(f"trial_fn: {trial_fn!r} cannot be sent to worker processes "
                             f"({exc}); use a top-level function of an importable module"
                             ) from exc

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    con = _connect(out / DB_NAME)
    try:
        if study is not None:
            _claim(con, out / DB_NAME, study)
        if not resume:
            con.execute("BEGIN IMMEDIATE")
            con.execute("DELETE FROM rows")
            con.execute("DELETE FROM trials")
            con.execute("COMMIT")
        stored = _done_keys(con, retry_failed=retry_failed)
        todo = [t for t in sorted(trials, key=lambda t: t.index) if t.key not in stored]
        skipped = len(trials) - len(todo)
        stale = _stale_count(con, todo)
        if stale:
            # said, not silent: a rerun that takes longer than the user expects has a reason
            print(f"studies: {stale} trial(s) stored in {out / DB_NAME} with the same index "
                  "and parameters were run by other code or on other inputs (the seed, the "
                  "scene or a file it reads, a method's source, reglib / testbed / studies "
                  "or a library's version changed since); they are run again",
                  file=sys.stderr)
        executed = 0
        bar = _progress(len(trials), skipped, progress)

        def record(trial: Trial, res: TrialResult) -> None:
            nonlocal executed
            _store(con, trial, res)
            executed += 1
            bar.update(1)
            if res.status == "failed":
                bar.set_postfix_str(f"last failure: trial {trial.index}", refresh=False)

        try:
            if not todo:
                pass
            elif scheduler is not None:
                _run_dask(trial_fn, todo, record, scheduler=scheduler, retries=retries)
            elif not pooled:
                _run_local(trial_fn, todo, record)
            else:
                _run_pool(trial_fn, todo, record, workers=int(workers), mp_context=mp_context,
                          retries=retries, timeout_s=timeout_s)
        finally:
            bar.close()
    finally:
        con.close()
    df = read_results(out, trials)
    df.attrs["executed"] = executed
    df.attrs["skipped"] = skipped
    df.attrs["stale"] = stale
    return df


#: the packages whose source a trial's result depends on (:func:`code_fingerprint`)
CODE_PACKAGES = ("reglib", "testbed", "studies")
#: the installed libraries whose versions do too (a numerical library upgraded changes
#: results as an edit of ours does)
CODE_LIBRARIES = ("numpy", "scipy", "numba", "trimesh", "embreex", "pybullet",
                  "opencv-python-headless", "scikit-image")


def installed_versions(libraries=CODE_LIBRARIES) -> dict:
    """Library -> its installed version (None: not installed), for ``libraries`` (pip
    distribution names)."""
    import importlib.metadata

    out = {}
    for lib in libraries:
        try:
            out[lib] = importlib.metadata.version(lib)
        except importlib.metadata.PackageNotFoundError:
            out[lib] = None
    return out


@functools.cache
def code_fingerprint(packages: tuple[str, ...] = CODE_PACKAGES) -> str:
    """:func:`fingerprint` of the code a trial runs: every ``*.py`` file of ``packages``
    (by path relative to the package, and bytes) and the versions of
    :data:`CODE_LIBRARIES`. Part of every study's and score's trial keys: results stored
    by other code are run again, not taken from ``trials.sqlite`` (a review found a score
    and a study reusing results after reglib was edited). Computed once per process."""
    import importlib.util

    texts = []
    files = []
    for name in packages:
        spec = importlib.util.find_spec(name)
        if spec is None or not spec.submodule_search_locations:
            texts.append(f"{name}: not found")
            continue
        root = Path(next(iter(spec.submodule_search_locations)))
        for f in sorted(root.rglob("*.py")):
            if "__pycache__" in f.parts:
                continue
            texts.append(f"{name}/{f.relative_to(root).as_posix()}")
            files.append(f)
    texts += [f"{lib}=={v}" if v is not None else f"{lib}: not installed"
              for lib, v in installed_versions().items()]
    # the files by their bytes alone: where the checkout lies does not change a result
    h = hashlib.sha256()
    h.update(fingerprint(texts=texts).encode())
    for f in files:
        h.update(b"\0")
        h.update(f.read_bytes())
    return h.hexdigest()


def scene_fingerprint(scene) -> str:
    """:func:`fingerprint` of a resolved scene (its every field, defaults included), of
    the files it names (a phantom mesh, a robot URDF) and of the code that runs it
    (:func:`code_fingerprint`): a study rerun into the same folder after the scene file, a
    file it reads, or reglib / testbed / studies changed runs its trials again."""
    if scene is None or not hasattr(scene, "model_dump"):
        return ""
    from testbed.generate import scene_digest  # the digest a dataset records of its scene

    files = [p for p in (getattr(getattr(scene, "phantom", None), "mesh_path", None),
                         getattr(getattr(scene, "robot", None), "urdf", None))
             if p and p != "builtin"]
    return fingerprint(texts=[scene_digest(scene), code_fingerprint()], files=files)


def run_study_trials(ctx, trial_fn: Callable[[Trial], list[dict]],
                     params: Sequence[Mapping[str, Any]], *, scheduler=None,
                     progress: bool | None = None, **kwargs) -> pd.DataFrame:
    """:func:`run_trials` for a study: trials on ``ctx.scene_path`` seeded from ``ctx.seed``
    (trial ``i`` = child ``i`` of ``SeedSequence(ctx.seed)``, as ``ctx.seeds``), stored in
    ``ctx.out``, on ``ctx.workers`` workers or on ``scheduler`` (default:
    ``ctx.scheduler`` if the context has one). Other keywords go to :func:`run_trials`.

    Parameters
    ----------
    ctx : studies.common.StudyContext
        Needs ``scene_path``, ``seed``, ``out`` and ``workers``.
    trial_fn : callable
        Top-level ``trial_fn(trial) -> list[dict]``; it loads the scene from ``trial.scene``.
    params : sequence of dict
        One dict of scalar parameters per trial.
    """
    trials = make_trials(str(ctx.scene_path), int(ctx.seed), params,
                         fingerprint=scene_fingerprint(ctx.scene))
    return run_context_trials(ctx, trial_fn, trials, scheduler=scheduler, progress=progress,
                              **kwargs)


def run_context_trials(ctx, trial_fn: Callable[[Trial], list[dict]], trials: list[Trial], *,
                       scheduler=None, progress: bool | None = None, **kwargs) -> pd.DataFrame:
    """:func:`run_trials` of ready-made ``trials`` with the study context's options: its
    folder, workers, scheduler, retries, progress, owner and ``retry_failed`` (other
    keywords go to :func:`run_trials`)."""
    if scheduler is None:
        scheduler = getattr(ctx, "scheduler", None)
    scene = getattr(ctx, "scene", None)
    if scheduler is None and getattr(getattr(scene, "scene", None), "kind", "") \
            == "operating_room" and getattr(scene, "views", None):
        # the workers' cases at once must fit before the first starts (a trial refused
        # inside a worker for what the others hold would depend on the machine's load)
        from testbed.simulate import check_memory

        check_memory(scene, workers=int(ctx.workers))
    kwargs.setdefault("retries", getattr(ctx, "retries", 2))
    if progress is None:  # the study's choice (testbed study: only on a terminal)
        progress = bool(getattr(ctx, "progress", True))
    kwargs.setdefault("study", getattr(ctx, "owner", None) or getattr(ctx, "name", None))
    kwargs.setdefault("retry_failed", bool(getattr(ctx, "retry_failed", False)))
    return run_trials(trial_fn, trials, out_dir=ctx.out, workers=int(ctx.workers),
                      scheduler=scheduler, progress=progress, **kwargs)
