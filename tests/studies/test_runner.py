"""The study runner: same rows on any number of workers (in-process, process pool, Dask),
resume after SIGKILL without loss or rerun, failures recorded without stopping the study.
Also the summaries of studies.report, on the runner's results (failures included)."""

from __future__ import annotations

import hashlib
import json
import os
import signal
import sqlite3
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from studies.common import start_study
from studies.report import plot_metric, success_rate, summarize
from studies.runner import (
    DB_NAME,
    Trial,
    _process_alive,
    make_trials,
    read_failures,
    read_results,
    read_trials,
    run_study_trials,
    run_trials,
)

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
PINS = ("proximal", "distal_1", "distal_2")


def toy_trial(trial: Trial) -> list[dict]:
    """A tiny trial: a few random numbers from the trial's seed, a short sleep, and on demand
    an exception (``fail``), malformed rows (``bad_rows``) or a dead worker (``die``)."""
    p = trial.params
    rng = trial.rng()
    if p.get("pid_dir"):     # say which process runs it
        (Path(p["pid_dir"]) / str(os.getpid())).touch()
    if p.get("bar"):         # a progress bar, as a method's inner loop may draw (disabled)
        from tqdm import tqdm

        tqdm(total=1, disable=True).close()
    if p.get("child_dir"):   # start a helper program that would outlive the trial
        child = subprocess.Popen(["sleep", "300"])
        (Path(p["child_dir"]) / str(child.pid)).touch()
    time.sleep(p.get("sleep_s", 0.0))
    if p.get("fail"):
        raise RuntimeError(f"trial {trial.index} was asked to fail")
    if p.get("odd"):       # exceptions a user's method may raise that are hard to report
        raise _odd_exception(p["odd"])
    if p.get("die"):
        os._exit(3)
    if p.get("chatty"):      # a method that prints
        for i in range(50):
            print("working", i, flush=True)
    if p.get("keyint"):      # a method that raises KeyboardInterrupt by itself
        raise KeyboardInterrupt
    if p.get("die_times"):  # the first die_times runs lose their worker, then it succeeds
        mark = Path(p["mark_dir"]) / f"died-{trial.index}"
        n = int(mark.read_text()) if mark.exists() else 0
        if n < p["die_times"]:
            mark.write_text(str(n + 1))
            os._exit(3)
    if p.get("bad_rows"):
        return [{"metric": "mtre", "value": "2 mm", "unit": "mm"}]
    rows = [{"metric": "pin_error", "value": float(v), "unit": "mm", "pin": pin}
            for pin, v in zip(PINS, rng.gamma(2.0, 0.5, size=3))]
    rows.append({"metric": "mtre", "value": float(rng.normal(1.0, 0.1)), "unit": "mm"})
    rows.append({"metric": "undefined", "value": float("nan"), "unit": ""})
    return rows


class _OwnBase(BaseException):
    """A method's exception that is no Exception."""


class _Unprintable(Exception):
    def __str__(self):
        raise RuntimeError("cannot print me")


def _odd_exception(kind: str) -> BaseException:
    return {"base": _OwnBase("derived from BaseException"),
            "unprintable": _Unprintable(),
            "surrogate": ValueError("bad \udcff byte in a name"),
            "markdown": ValueError("first line\n## Injected heading\n```\n" + "x" * 9000)
            }[kind]


def expected_rows(study_seed: int, params: list[dict]) -> pd.DataFrame:
    """The rows computed directly from SeedSequence(study_seed).spawn(n), without the runner."""
    recs = []
    for i, (ss, p) in enumerate(zip(np.random.SeedSequence(study_seed).spawn(len(params)),
                                    params)):
        rng = np.random.default_rng(ss)
        g = rng.gamma(2.0, 0.5, size=3)
        for pin, v in zip(PINS, g):
            recs.append({"trial": i, "metric": "pin_error", "value": v, "unit": "mm", **p,
                         "pin": pin})
        recs.append({"trial": i, "metric": "mtre", "value": rng.normal(1.0, 0.1), "unit": "mm",
                     **p})
        recs.append({"trial": i, "metric": "undefined", "value": np.nan, "unit": "", **p})
    return pd.DataFrame(recs)


def _params(n, sleep_s=0.003):
    return [{"sleep_s": sleep_s, "noise": 0.1 * (i % 3)} for i in range(n)]


def test_trial_seed_is_the_spawned_child_and_rebuilds_exactly():
    children = np.random.SeedSequence(1234).spawn(5)
    trials = make_trials("points-lines", 1234, [{}] * 5)
    for child, t in zip(children, trials):
        assert (t.entropy, t.spawn_key) == (child.entropy, child.spawn_key)
        a = t.rng().random(4)
        b = np.random.default_rng(child).random(4)
        assert np.array_equal(a, b)
    assert len({t.key for t in trials}) == 5
    # the key changes with the seed and the parameters
    assert make_trials("points-lines", 1235, [{}])[0].key != trials[0].key
    assert make_trials("points-lines", 1234, [{"a": 1}])[0].key != trials[0].key
    # and with the fingerprint of what the trial reads; without one, the key is the one
    # trials stored before fingerprints had (their folders resume as they did)
    assert make_trials("points-lines", 1234, [{}], fingerprint="x")[0].key != trials[0].key
    t = trials[0]
    legacy = json.dumps([t.index, t.scene, t.entropy, list(t.spawn_key), t.params],
                        sort_keys=True, allow_nan=True)
    assert t.key == hashlib.sha1(legacy.encode()).hexdigest()


def test_scene_fingerprint_follows_the_scene_and_the_files_it_reads(tmp_path):
    """A study rerun into its folder after its scene changed must not take the stored trials
    for its own: the fingerprint follows every resolved field and a named file's bytes."""
    from studies.runner import fingerprint, scene_fingerprint
    from testbed.scene import find_scene, load_scene

    scene = load_scene(find_scene("experiment2"))
    same = load_scene(find_scene("experiment2"))
    assert scene_fingerprint(scene) == scene_fingerprint(same)
    moved = scene.model_copy(update={"scene": scene.scene.model_copy(update={"seed": 1})})
    assert scene_fingerprint(moved) != scene_fingerprint(scene)
    f = tmp_path / "a.txt"
    f.write_text("one")
    before = fingerprint(files=[f])
    f.write_text("two")
    assert fingerprint(files=[f]) != before
    assert fingerprint(files=[tmp_path / "none"]) != fingerprint(files=[f])


@pytest.mark.slow
def test_same_rows_in_process_and_on_two_workers(tmp_path):
    params = _params(10, sleep_s=0.02)
    trials = make_trials("points-lines", 42, params)
    one = run_trials(toy_trial, trials, out_dir=tmp_path / "w1", workers=1, progress=False)
    two = run_trials(toy_trial, trials, out_dir=tmp_path / "w2", workers=2, progress=False)
    pd.testing.assert_frame_equal(one, two)
    # and both are the rows computed straight from the seeds (NaN kept as NaN)
    exp = expected_rows(42, params)
    pd.testing.assert_frame_equal(one[exp.columns.tolist()], exp, check_exact=True)
    assert list(one.columns[:4]) == ["trial", "metric", "value", "unit"]
    assert one.attrs["executed"] == 10 and one.attrs["skipped"] == 0
    # the trials ran in two worker processes, none of them this one
    workers = set(read_trials(tmp_path / "w2").worker)
    assert len(workers) == 2 and all(not w.endswith(f":{os.getpid()}") for w in workers)


def test_failed_trial_is_recorded_and_does_not_stop_the_study(tmp_path):
    params = _params(6, sleep_s=0.0)
    params[2] = {**params[2], "fail": True}
    params[4] = {**params[4], "bad_rows": True}
    trials = make_trials("points-lines", 5, params)
    df = run_trials(toy_trial, trials, out_dir=tmp_path, progress=False)
    failed = df[df.metric == "failed"]
    assert failed.trial.tolist() == [2, 4]
    assert (failed.value == 1.0).all()
    assert sorted(set(df.trial)) == list(range(6))
    assert (df[df.trial == 3].metric == "mtre").sum() == 1
    fails = read_failures(tmp_path)
    assert fails.trial.tolist() == [2, 4]
    assert fails.error[0] == "RuntimeError: trial 2 was asked to fail"
    assert "toy_trial" in fails.traceback[0] and "RuntimeError" in fails.traceback[0]
    assert "trial 4, row 0 (mtre): 'value' must be a real number, got str" in fails.error[1]
    assert list(df.attrs["failures"]) == [2, 4]
    # resume: nothing to do; retry_failed runs only the two failed trials again
    again = run_trials(toy_trial, trials, out_dir=tmp_path, progress=False)
    assert again.attrs["executed"] == 0 and again.attrs["skipped"] == 6
    pd.testing.assert_frame_equal(again, df)
    assert pd.concat([df, again]).shape[0] == 2 * len(df)  # attrs do not break pandas
    retried = run_trials(toy_trial, trials, out_dir=tmp_path, progress=False, retry_failed=True)
    assert retried.attrs["executed"] == 2


@pytest.mark.parametrize("workers", [1, 2])
def test_odd_exceptions_are_failed_trials_that_a_report_can_show(tmp_path, workers):
    # a review's methods raised a BaseException of their own, an exception whose __str__
    # raises, a message SQLite cannot encode (a lone surrogate) and a 5 MB message with a
    # markdown heading and an open code fence: the first three ended the command with no
    # results (on every rerun), the last broke report.md's sections
    params = _params(6, sleep_s=0.0)
    kinds = {1: "base", 2: "unprintable", 3: "surrogate", 4: "markdown"}
    for i, kind in kinds.items():
        params[i] = {**params[i], "odd": kind}
    trials = make_trials("points-lines", 3, params)
    df = run_trials(toy_trial, trials, out_dir=tmp_path, workers=workers, progress=False)
    assert df[df.metric == "failed"].trial.tolist() == [1, 2, 3, 4]
    ok = df[~df.trial.isin(kinds)].reset_index(drop=True)
    exp = expected_rows(3, params)
    exp = exp[~exp.trial.isin(kinds)].reset_index(drop=True)
    pd.testing.assert_frame_equal(ok[exp.columns.tolist()], exp, check_exact=True)
    full = read_failures(tmp_path).set_index("trial").error
    assert full[1] == "_OwnBase: derived from BaseException"
    assert full[2] == "_Unprintable: (its message cannot be printed: RuntimeError)"
    assert full[3] == "ValueError: bad \\udcff byte in a name"
    assert full[4].startswith("ValueError: first line\n## Injected heading")
    assert "characters cut" in full[4] and len(full[4]) < 4100
    shown = df.attrs["failures"]
    assert shown[4].startswith("ValueError: first line / ## Injected heading / \\`\\`\\` / xxx")
    assert shown[4].endswith("... (the whole message: read_failures or trials.sqlite)")
    assert all("\n" not in v and len(v) < 400 for v in shown.values())
    # stored: a rerun takes them from the database instead of failing again
    again = run_trials(toy_trial, trials, out_dir=tmp_path, workers=workers, progress=False)
    assert again.attrs["executed"] == 0


def test_resume_false_reruns_and_other_trials_are_not_returned(tmp_path):
    a = make_trials("points-lines", 1, _params(3, 0.0))
    b = make_trials("points-lines", 2, _params(3, 0.0))
    ra = run_trials(toy_trial, a, out_dir=tmp_path, progress=False)
    rb = run_trials(toy_trial, b, out_dir=tmp_path, progress=False)
    assert rb.attrs["executed"] == 3  # other seeds: other keys, nothing reused
    assert not np.array_equal(ra.value.to_numpy()[:3], rb.value.to_numpy()[:3])
    pd.testing.assert_frame_equal(read_results(tmp_path, a), ra)
    fresh = run_trials(toy_trial, a, out_dir=tmp_path, progress=False, resume=False)
    assert fresh.attrs["executed"] == 3
    pd.testing.assert_frame_equal(fresh, ra)
    assert len(read_trials(tmp_path)) == 3  # resume=False emptied the database


def test_bad_input_is_refused_with_a_clear_message(tmp_path):
    t = make_trials("points-lines", 0, [{}, {}])
    with pytest.raises(ValueError, match="index 0 is used twice"):
        run_trials(toy_trial, [t[0], t[0]], out_dir=tmp_path)
    with pytest.raises(ValueError, match="workers: expected an int >= 1"):
        run_trials(toy_trial, t, out_dir=tmp_path, workers=0)
    with pytest.raises(ValueError, match="trial_fn: .* cannot be sent to worker processes"):
        run_trials(lambda t: [], t, out_dir=tmp_path, workers=2)
    with pytest.raises(ValueError, match="parameter 'value' clashes"):
        Trial(0, "points-lines", 1, (0,), {"value": 3})
    with pytest.raises(ValueError, match="parameter 'x': expected a scalar"):
        Trial(0, "points-lines", 1, (0,), {"x": [1, 2]})
    with pytest.raises(ValueError, match="study_seed must be an int >= 0"):
        make_trials("points-lines", -1, [{}])


@pytest.mark.slow
def test_worker_that_dies_is_recorded_and_the_others_finish(tmp_path):
    params = _params(6, sleep_s=0.01)
    params[3] = {**params[3], "die": True}
    trials = make_trials("points-lines", 9, params)
    df = run_trials(toy_trial, trials, out_dir=tmp_path, workers=2, progress=False)
    assert df[df.metric == "failed"].trial.tolist() == [3]
    assert "WorkerLost" in read_failures(tmp_path).error[0]
    ok = df[df.trial != 3].reset_index(drop=True)
    exp = expected_rows(9, params)
    exp = exp[exp.trial != 3].reset_index(drop=True)
    pd.testing.assert_frame_equal(ok[exp.columns.tolist()], exp, check_exact=True)


def test_a_keyboard_interrupt_raised_by_a_trial_in_a_worker_is_its_failure(tmp_path):
    """A method that raises KeyboardInterrupt itself (nobody pressed Ctrl-C, which no longer
    reaches the workers) ended the whole command with exit 130 and no results, on every
    rerun (a review); in a worker it is now that trial's failure."""
    params = _params(4, sleep_s=0.01)
    params[2] = {**params[2], "keyint": True}
    trials = make_trials("points-lines", 13, params)
    df = run_trials(toy_trial, trials, out_dir=tmp_path, workers=2, progress=False)
    assert df[df.metric == "failed"].trial.tolist() == [2]
    assert read_failures(tmp_path).error[0].startswith("KeyboardInterrupt")
    assert sorted(df[df.metric == "mtre"].trial) == [0, 1, 3]
    with pytest.raises(KeyboardInterrupt):   # in the study's own process it is an interrupt
        run_trials(toy_trial, trials, out_dir=tmp_path / "here", workers=1, progress=False)


@pytest.mark.parametrize("workers", [1, 2])
def test_a_trial_past_its_time_limit_is_recorded_and_the_others_finish(tmp_path, workers):
    # a method that hangs (here: sleeps far past the limit) must not hold the study: its
    # trial is failed as timed out, its worker killed, and every other trial gives the rows
    # of an unlimited run, among them one in flight beside it when the pool was killed
    params = _params(5, sleep_s=0.3)
    children = tmp_path / "children"
    children.mkdir()
    params[1] = {**params[1], "sleep_s": 300.0, "child_dir": str(children)}
    trials = make_trials("points-lines", 11, params)
    t0 = time.monotonic()
    df = run_trials(toy_trial, trials, out_dir=tmp_path, workers=workers, progress=False,
                    timeout_s=4.0)
    assert time.monotonic() - t0 < 60.0
    assert df[df.metric == "failed"].trial.tolist() == [1]
    # the program the hung trial started is killed with its worker (it lived on, a review)
    (child,) = [int(f.name) for f in children.iterdir()]
    gone = time.monotonic() + 10.0
    while _process_alive(child) and time.monotonic() < gone:
        time.sleep(0.05)
    assert not _process_alive(child)
    err = read_failures(tmp_path).error[0]
    assert err.startswith("TimedOut: the trial still ran after 4 s"), err
    ok = df[df.trial != 1].reset_index(drop=True)
    exp = expected_rows(11, params)
    exp = exp[exp.trial != 1].reset_index(drop=True)
    pd.testing.assert_frame_equal(ok[exp.columns.tolist()], exp, check_exact=True)
    with pytest.raises(ValueError, match="timeout_s: expected a number of seconds > 0"):
        run_trials(toy_trial, trials, out_dir=tmp_path, timeout_s=0, progress=False)
    with pytest.raises(ValueError, match="needs local workers"):
        run_trials(toy_trial, trials, out_dir=tmp_path, timeout_s=5.0, progress=False,
                   scheduler="tcp://127.0.0.1:1")


@pytest.mark.slow
@pytest.mark.parametrize("retries, die_times, ok", [(2, 2, True), (1, 3, False), (0, 2, False)])
def test_lost_workers_are_retried_a_bounded_number_of_times(tmp_path, retries, die_times, ok):
    # the first death is in the shared pool (every trial in flight becomes a suspect and is
    # rerun alone); then up to retries + 1 runs alone before the trial is recorded as failed
    params = _params(4, sleep_s=0.01)
    params[1] = {**params[1], "die_times": die_times, "mark_dir": str(tmp_path)}
    trials = make_trials("points-lines", 5, params)
    df = run_trials(toy_trial, trials, out_dir=tmp_path / "s", workers=2, progress=False,
                    retries=retries)
    failed = df[df.metric == "failed"].trial.tolist()
    assert failed == ([] if ok else [1])
    runs = int((tmp_path / "died-1").read_text()) + (1 if ok else 0)
    assert runs == (die_times + 1 if ok else 1 + retries + 1)
    if not ok:
        assert f"{retries + 1} attempt(s) alone" in read_failures(tmp_path / "s").error[0]
    exp = expected_rows(5, [{k: v for k, v in p.items() if k in ("sleep_s", "noise")}
                            for p in params])
    got = df[df.trial != 1] if not ok else df
    exp = exp[exp.trial.isin(got.trial.unique())].reset_index(drop=True)
    cols = [c for c in exp.columns if c in got.columns]
    pd.testing.assert_frame_equal(got.reset_index(drop=True)[cols], exp[cols],
                                  check_exact=True, check_dtype=False)


def test_a_pool_that_breaks_between_two_submissions_loses_nothing(tmp_path, monkeypatch):
    # a worker may die after the last wait and before the next submit, which then raises
    # BrokenProcessPool itself (it crashed a whole study): the unsubmitted trial goes back in
    # line, the trials that finished keep their results, and every row is as expected
    import concurrent.futures as cf
    from concurrent.futures.process import BrokenProcessPool

    import studies.runner as runner

    calls = {"n": 0}

    class BreaksOnce(cf.ProcessPoolExecutor):
        def submit(self, fn, /, *args, **kwargs):
            calls["n"] += 1
            if calls["n"] == 3:
                raise BrokenProcessPool("a worker died between two submissions (simulated)")
            return super().submit(fn, *args, **kwargs)

    monkeypatch.setattr(runner.cf, "ProcessPoolExecutor", BreaksOnce)
    params = _params(5, sleep_s=0.01)
    df = run_trials(toy_trial, make_trials("points-lines", 8, params), out_dir=tmp_path / "s",
                    workers=2, progress=False)
    assert calls["n"] >= 6  # the refused submission was made again
    assert "failed" not in set(df.metric)
    exp = expected_rows(8, params)
    pd.testing.assert_frame_equal(df.reset_index(drop=True)[exp.columns.tolist()], exp,
                                  check_exact=True, check_dtype=False)


class _KilledWorker(Exception):
    pass


_KilledWorker.__name__ = "KilledWorker"  # as distributed.scheduler.KilledWorker


def test_dask_killed_worker_is_retried_then_recorded(tmp_path, monkeypatch):
    """_run_dask on a fake client: a KilledWorker is retried ``retries`` times, then the
    trial is recorded as failed; an error of the trial itself is not retried."""
    import distributed

    from studies.runner import execute_trial

    submitted: list[int] = []

    class Fut:
        def __init__(self, trial, attempt, kw):
            self.trial, self.attempt, self.kw = trial, attempt, kw

        def result(self):
            kills = self.trial.params.get("kills", 0)
            if self.attempt < kills:
                raise _KilledWorker(f"attempt {self.attempt} lost its worker")
            return execute_trial(toy_trial, self.trial, **self.kw)

    class FakeClient:
        def submit(self, fn, trial_fn, trial, pure=False, key=None, **kw):
            assert fn is execute_trial and trial_fn is toy_trial
            submitted.append(trial.index)
            return Fut(trial, submitted.count(trial.index) - 1, kw)

        def cancel(self, futs):
            pass

    class AsCompleted:
        def __init__(self, futs):
            self.queue = list(futs)

        def add(self, fut):
            self.queue.append(fut)

        def __iter__(self):
            while self.queue:
                yield self.queue.pop(0)

    monkeypatch.setattr(distributed, "Client", FakeClient)
    monkeypatch.setattr(distributed, "as_completed", AsCompleted)
    # a trial's own KeyboardInterrupt on a Dask worker (where no Ctrl-C of the study's
    # terminal arrives) is its failure, as in a pool worker
    params = [{"kills": 0}, {"kills": 2}, {"kills": 3}, {"fail": True}, {"keyint": True}]
    trials = make_trials("points-lines", 3, params)
    df = run_trials(toy_trial, trials, out_dir=tmp_path, scheduler=FakeClient(),
                    progress=False, retries=2)
    assert sorted(df[df.metric == "failed"].trial.unique().tolist()) == [2, 3, 4]
    assert submitted.count(0) == 1 and submitted.count(1) == 3 and submitted.count(2) == 3
    assert submitted.count(3) == 1  # the trial's own error: no retry
    fails = read_failures(tmp_path).set_index("trial").error
    assert "KilledWorker" in fails[2] and "after 3 attempts" in fails[2]
    assert "asked to fail" in fails[3] and fails[4].startswith("KeyboardInterrupt")
    ok = df[df.trial.isin([0, 1])]
    assert set(ok.metric) >= {"pin_error", "mtre"}


def _count_done(db: Path) -> int:
    if not db.exists():
        return 0
    try:
        with sqlite3.connect(db, timeout=5) as con:
            return con.execute("SELECT COUNT(*) FROM trials").fetchone()[0]
    except sqlite3.OperationalError:  # tables not created yet
        return 0


@pytest.mark.slow
def test_resume_after_sigkill_gives_the_rows_of_an_uninterrupted_run(tmp_path):
    n, seed = 30, 77
    params = _params(n, sleep_s=0.04)
    killed = tmp_path / "killed"
    script = tmp_path / "study.py"
    script.write_text(textwrap.dedent(f"""
        import sys
        sys.path.insert(0, {str(HERE)!r})
        from studies.runner import make_trials, run_trials
        from test_runner import _params, toy_trial

        if __name__ == "__main__":
            trials = make_trials("points-lines", {seed}, _params({n}, sleep_s=0.04))
            run_trials(toy_trial, trials, out_dir={str(killed)!r}, workers=2, progress=False)
    """))
    proc = subprocess.Popen([sys.executable, str(script)], cwd=ROOT, start_new_session=True,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    db = killed / DB_NAME
    try:
        deadline = time.monotonic() + 120
        while _count_done(db) < 4:
            assert proc.poll() is None, proc.stderr.read().decode()
            assert time.monotonic() < deadline, "the study never stored 4 trials"
            time.sleep(0.02)
    finally:
        # kill -9 of the study's process: its workers, in groups of their own, end by
        # themselves (test_workers_end_when_the_study_is_killed); the semaphore tracker
        # lives on to unlink the pool's semaphores (killed with the study's group, it
        # left 5 files in /dev/shm per run)
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        proc.stderr.close()
    before = read_trials(killed)
    assert 4 <= len(before) < n, "the kill came too late to test a resume"

    trials = make_trials("points-lines", seed, params)
    resumed = run_trials(toy_trial, trials, out_dir=killed, workers=1, progress=False)
    assert resumed.attrs["skipped"] == len(before)
    assert resumed.attrs["executed"] == n - len(before)
    after = read_trials(killed).set_index("key")
    # trials stored before the kill were not run again
    assert (after.loc[before.key, "worker"].to_numpy() == before.worker.to_numpy()).all()

    clean = run_trials(toy_trial, trials, out_dir=tmp_path / "clean", workers=1,
                       progress=False)
    pd.testing.assert_frame_equal(resumed, clean, check_exact=True)
    assert len(clean) == 5 * n


def test_workers_that_print_to_a_tostop_terminal_are_not_stopped(tmp_path):
    """The workers lead process groups of their own, in the terminal's background: under
    `stty tostop` a trial that printed stopped its worker (SIGTTOU) and the study hung for
    good (a review). Run in a pseudo-terminal with TOSTOP set."""
    import pty
    import select
    import termios

    script = tmp_path / "study.py"
    script.write_text(textwrap.dedent(f"""
        import sys, termios
        attrs = termios.tcgetattr(0)
        attrs[3] |= termios.TOSTOP
        termios.tcsetattr(0, termios.TCSANOW, attrs)
        sys.path.insert(0, {str(HERE)!r})
        from studies.runner import make_trials, run_trials
        from test_runner import toy_trial

        if __name__ == "__main__":
            trials = make_trials("points-lines", 5, [{{"chatty": True}}] * 2)
            df = run_trials(toy_trial, trials, out_dir={str(tmp_path / "out")!r}, workers=2,
                            progress=False)
            print("DONE", sorted(set(df.metric)), flush=True)
    """))
    pid, fd = pty.fork()
    if pid == 0:     # the child: a session of its own with the pty as its terminal
        os.chdir(ROOT)
        os.execv(sys.executable, [sys.executable, str(script)])
    out, deadline = b"", time.monotonic() + 90
    try:
        while time.monotonic() < deadline and b"DONE" not in out:
            ready, _, _ = select.select([fd], [], [], 1.0)
            if ready:
                try:
                    out += os.read(fd, 65536)
                except OSError:          # the child closed the terminal
                    break
    finally:
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        os.waitpid(pid, 0)
        os.close(fd)
    assert b"DONE" in out and b"failed" not in out.split(b"DONE")[1], out[-2000:]
    assert termios.TOSTOP   # (the flag the child set)


def _study_with_workers(tmp_path, *, sleep_s: float, trials: int):
    """A study of ``trials`` sleeping toy trials on 2 workers, in a process of its own:
    ``(Popen, worker pids)`` once both workers run a trial (the study checks that none
    failed)."""
    pids = tmp_path / "pids"
    pids.mkdir()
    script = tmp_path / "study.py"
    script.write_text(textwrap.dedent(f"""
        import sys
        sys.path.insert(0, {str(HERE)!r})
        from studies.runner import make_trials, run_trials
        from test_runner import toy_trial

        if __name__ == "__main__":
            params = [{{"sleep_s": {sleep_s}, "pid_dir": {str(pids)!r}}}] * {trials}
            trials = make_trials("points-lines", 5, params)
            df = run_trials(toy_trial, trials, out_dir={str(tmp_path / "out")!r}, workers=2,
                            progress=False)
            assert "failed" not in set(df.metric)
    """))
    proc = subprocess.Popen([sys.executable, str(script)], cwd=ROOT,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 120
    while len(list(pids.iterdir())) < 2:
        assert proc.poll() is None, proc.stderr.read().decode()
        assert time.monotonic() < deadline, "the workers never started their trials"
        time.sleep(0.05)
    return proc, [int(f.name) for f in pids.iterdir()]


def _state(pid: int) -> str:
    with open(f"/proc/{pid}/stat") as f:
        return f.read().rsplit(")", 1)[1].split()[0]


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs /proc")
def test_ctrl_z_stops_the_workers_with_the_study_and_sigcont_resumes_them(tmp_path):
    """The workers lead process groups of their own, so a terminal's Ctrl-Z (SIGTSTP)
    stopped the study's process alone and its workers went on computing (a review); now
    they stop with it, and resume on SIGCONT."""
    proc, workers = _study_with_workers(tmp_path, sleep_s=4.0, trials=2)
    try:
        os.kill(proc.pid, signal.SIGTSTP)
        deadline = time.monotonic() + 10
        while not all(_state(p) == "T" for p in [proc.pid, *workers]):
            assert time.monotonic() < deadline, [_state(p) for p in [proc.pid, *workers]]
            time.sleep(0.05)
        time.sleep(0.5)
        assert all(_state(p) == "T" for p in workers)       # still stopped
        os.kill(proc.pid, signal.SIGCONT)
        deadline = time.monotonic() + 10
        while any(_state(p) == "T" for p in workers if _process_alive(p)):
            assert time.monotonic() < deadline, "the workers were not resumed"
            time.sleep(0.05)
        assert proc.wait(timeout=60) == 0, proc.stderr.read().decode()
    finally:
        if proc.poll() is None:
            os.kill(proc.pid, signal.SIGCONT)
            proc.kill()
            proc.wait()
        proc.stderr.close()


@pytest.mark.slow
def test_a_time_limit_counts_from_the_trials_start_not_its_workers(tmp_path):
    """A worker's start and the imports it makes before its first trial are not the trial's
    time: a trial of 0.2 s whose worker took 5 s to import the method's module finishes
    under a limit of 2 s (the limit counted from the hand-over, and a loaded CI machine
    timed out a toy trial). A worker that has not started a trial within the limit plus
    START_GRACE_S is still stopped, with a message that says so."""
    (tmp_path / "slow_import.py").write_text(textwrap.dedent("""
        import os
        import time
        if os.getpid() != int(os.environ["STUDY_PID"]):  # slow in the workers alone
            time.sleep(5.0)

        def trial(t):
            time.sleep(0.2)
            return [{"metric": "x", "value": 1.0, "unit": "1"}]
    """))
    script = tmp_path / "study.py"
    script.write_text(textwrap.dedent(f"""
        import os
        import sys
        os.environ.setdefault("STUDY_PID", str(os.getpid()))  # a spawned worker keeps it
        sys.path.insert(0, {str(ROOT)!r})
        import studies.runner as runner
        from studies.runner import make_trials, read_failures, run_trials
        from slow_import import trial

        if __name__ == "__main__":
            out = {str(tmp_path)!r}
            # each spawned worker imports this script's modules first: 5 s
            runner.START_GRACE_S = 2.0
            df = run_trials(trial, make_trials("a", 1, [{{}}]), out_dir=out + "/a",
                            workers=1, progress=False, timeout_s=1.0, mp_context="spawn")
            assert list(df.metric) == ["failed"], df
            err = read_failures(out + "/a").error[0]
            assert err.startswith("TimedOut: no worker had started the trial 3 s"), err
            runner.START_GRACE_S = 120.0
            df = run_trials(trial, make_trials("b", 2, [{{}}, {{}}]), out_dir=out + "/b",
                            workers=2, progress=False, timeout_s=2.0, mp_context="spawn")
            assert list(df.metric) == ["x", "x"], (df, read_failures(out + "/b"))
    """))
    out = subprocess.run([sys.executable, str(script)], cwd=ROOT, capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stderr


def test_a_killed_worker_leaves_no_semaphore_behind(tmp_path):
    """A trial that drew a (disabled) tqdm bar made tqdm's inter-process lock, a semaphore;
    its worker killed at the time limit never released it, and every interrupted or
    timed-out study ended with the tracker's 'leaked semaphore objects' warning."""
    script = tmp_path / "study.py"
    script.write_text(textwrap.dedent(f"""
        import sys
        sys.path.insert(0, {str(HERE)!r})
        from studies.runner import make_trials, run_trials
        from test_runner import toy_trial

        if __name__ == "__main__":
            trials = make_trials("points-lines", 5, [{{"sleep_s": 300.0, "bar": True}}])
            df = run_trials(toy_trial, trials, out_dir={str(tmp_path / "out")!r}, workers=2,
                            progress=False, timeout_s=3.0)
            assert list(df.metric) == ["failed"], df
    """))
    out = subprocess.run([sys.executable, str(script)], cwd=ROOT, capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "leaked semaphore" not in out.stderr, out.stderr


@pytest.mark.slow
def test_workers_end_when_the_study_is_killed(tmp_path):
    """A study killed by SIGKILL (the OOM killer, a batch system's hard limit) cannot stop
    its pool: its workers end by themselves within seconds (a review found them idle for
    good, 0.8 GB each). The killed process is left unreaped, a zombie, as a parent that
    does not wait leaves it."""
    from studies.runner import PARENT_POLL_S

    proc, workers = _study_with_workers(tmp_path, sleep_s=120.0, trials=4)
    pids = tmp_path / "pids"
    try:
        assert all(_process_alive(w) for w in workers)
        os.kill(proc.pid, signal.SIGKILL)
        time.sleep(0.5)
        assert not _process_alive(proc.pid)       # a zombie counts as gone
        deadline = time.monotonic() + 10 * PARENT_POLL_S + 5
        while any(_process_alive(w) for w in workers):
            assert time.monotonic() < deadline, "the workers outlived the killed study"
            time.sleep(0.1)
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait()
        proc.stderr.close()
        for f in pids.iterdir():
            try:
                os.kill(int(f.name), signal.SIGKILL)
            except ProcessLookupError:
                pass


@pytest.mark.slow
def test_dask_local_cluster_gives_the_same_rows(tmp_path):
    distributed = pytest.importorskip("distributed")
    params = _params(8)
    trials = make_trials("points-lines", 3, params)
    ref = run_trials(toy_trial, trials, out_dir=tmp_path / "ref", progress=False)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster:
        by_cluster = run_trials(toy_trial, trials, out_dir=tmp_path / "c", scheduler=cluster,
                                progress=False)
        by_address = run_trials(toy_trial, trials, out_dir=tmp_path / "a",
                                scheduler=cluster.scheduler_address, progress=False)
    pd.testing.assert_frame_equal(by_cluster, ref, check_exact=True)
    pd.testing.assert_frame_equal(by_address, ref, check_exact=True)
    assert len(set(read_trials(tmp_path / "c").worker)) == 2


def test_study_context_runs_trials_seeded_by_the_study(tmp_path):
    ctx = start_study("toy", tmp_path, scene="points-lines", seed=11)
    params = _params(4, 0.0)
    df = run_study_trials(ctx, toy_trial, params, progress=False)
    exp = expected_rows(11, params)
    pd.testing.assert_frame_equal(df[exp.columns.tolist()], exp, check_exact=True)
    assert (tmp_path / DB_NAME).exists()
    assert set(read_trials(tmp_path).scene) == {str(ctx.scene_path)}


def test_report_summaries_count_failed_trials(tmp_path):
    params = [{"sleep_s": 0.0, "noise": float(i % 2)} for i in range(12)]
    for i in (3, 8):
        params[i] = {**params[i], "fail": True}
    df = run_trials(toy_trial, make_trials("points-lines", 21, params), out_dir=tmp_path,
                    progress=False)
    exp = expected_rows(21, [{k: v for k, v in p.items() if k != "fail"} for p in params])
    ok = exp[~exp.trial.isin([3, 8])]

    pins = summarize(df, "pin_error", by=["pin"])
    assert pins.pin.tolist() == sorted(PINS)
    assert (pins.n == 10).all() and (pins.failed == 2).all() and (pins.unit == "mm").all()
    for row in pins.itertuples():
        v = ok[(ok.metric == "pin_error") & (ok.pin == row.pin)].value.to_numpy()
        assert row.mean == pytest.approx(v.mean(), rel=1e-12)
        assert row.p95 == pytest.approx(np.quantile(v, 0.95), rel=1e-12)
    whole = summarize(df, "mtre")
    assert whole.n[0] == 10 and whole.failed[0] == 2

    rate = success_rate(df, "mtre", 1.0, by=["noise"])
    for row in rate.itertuples():
        trials = exp[(exp.noise == row.noise)].trial.unique()
        m = ok[(ok.metric == "mtre") & (ok.noise == row.noise)]
        assert row.trials == len(trials) == 6
        assert row.successes == int((m.value < 1.0).sum())
        assert row.lo <= row.rate <= row.hi
    # a trial with several rows succeeds only if all do
    allpins = success_rate(df, "pin_error", 1.0)
    per = ok[ok.metric == "pin_error"].groupby("trial").value.max() < 1.0
    assert allpins.successes[0] == int(per.sum()) and allpins.trials[0] == 12
    with pytest.raises(ValueError, match="no rows with metric 'nope'"):
        summarize(df, "nope")

    png = plot_metric(df, "mtre", "noise", tmp_path / "mtre.png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def _exits(trial):
    if trial.index == 1:
        raise SystemExit(3)          # a user's method that calls sys.exit
    return [{"metric": "mtre", "value": 1.0, "unit": "mm"}]


def test_a_trial_that_exits_is_a_failed_trial_and_the_command_says_so(tmp_path, capsys):
    """SystemExit in a trial is recorded as its failure (it used to end `testbed score` with
    its status and no results); the command then exits 1 with one line on stderr saying how
    many trials failed, after writing the others' results."""
    from studies.cli import _failed_trials

    df = run_trials(_exits, make_trials("points-lines", 3, [{}] * 3), out_dir=tmp_path,
                    workers=1, progress=False)
    failed = df[df.metric == "failed"]
    assert list(failed.trial) == [1]
    assert "SystemExit: 3" in read_failures(tmp_path).error.item()
    df.to_csv(tmp_path / "results.csv", index=False)
    assert _failed_trials(tmp_path) == 1
    assert "1 of 3 trial(s) failed" in capsys.readouterr().err
    # a study's summary rows (trial -1: capture_range, the confusion counts) are no trial
    summary = pd.DataFrame([{"trial": -1, "metric": "capture_range", "value": 30.0,
                             "unit": "mm"}])
    pd.concat([df, summary]).to_csv(tmp_path / "results.csv", index=False)
    assert _failed_trials(tmp_path) == 1
    assert "1 of 3 trial(s) failed" in capsys.readouterr().err
    df[df.metric != "failed"].to_csv(tmp_path / "results.csv", index=False)
    assert _failed_trials(tmp_path) == 0


def test_every_study_reports_when_no_trial_finished(tmp_path, monkeypatch, capsys):
    """Every trial failing (a scene whose cases cannot be simulated) still gives
    results.csv and a report.md that names the failures; three studies stopped with a
    KeyError of the empty table (a review: view-setups, then capture-range and fig9)."""
    import importlib

    from studies import _module_name, available_studies, run_study

    def fails(trial):
        raise RuntimeError("this case cannot be simulated")

    ran = []
    for name in available_studies():
        mod = importlib.import_module(_module_name(name))
        patched = [a for a in ("trial", "_trial") if hasattr(mod, a)]
        for a in patched:
            monkeypatch.setattr(mod, a, fails)
        if not patched:          # table1 times solves in its run, no trial function
            continue
        out = tmp_path / name
        run_study(name, out, quick=True, progress=False)
        df = pd.read_csv(out / "results.csv")
        assert len(df) and (df.metric == "failed").all(), name
        assert "this case cannot be simulated" in (out / "report.md").read_text(), name
        ran.append(name)
    assert len(ran) >= 8, ran
    assert "trials:" not in capsys.readouterr().err   # progress=False is kept by every study


def _interrupted_in_a_kernel(trial):
    try:
        raise KeyboardInterrupt
    except KeyboardInterrupt:   # as numba reports a Ctrl-C that arrived inside its code
        raise SystemError("CPUDispatcher(<function quantum_counts>) returned a result with "
                          "an exception set") from None


def test_an_interrupt_inside_compiled_code_stops_the_study(tmp_path, monkeypatch, capsys):
    """Ctrl-C while a numba function runs surfaces as a SystemError whose context is the
    interrupt; it was recorded as the trial's failure (the study went on, and a resume never
    ran that trial again: a review, table2 --quick interrupted at 7 s). It is an interrupt:
    nothing is stored, and the command exits 130."""
    import studies.cli as cli
    from studies.runner import execute_trial, interrupt_of

    (trial,) = make_trials("points-lines", 1, [{}])
    with pytest.raises(KeyboardInterrupt):
        execute_trial(_interrupted_in_a_kernel, trial)
    with pytest.raises(KeyboardInterrupt):
        run_trials(_interrupted_in_a_kernel, [trial], out_dir=tmp_path, workers=1,
                   progress=False)
    assert read_trials(tmp_path).empty if (tmp_path / DB_NAME).exists() else True
    assert interrupt_of(ValueError("plain")) is None

    def scenes(args):
        _interrupted_in_a_kernel(None)

    monkeypatch.setattr(cli, "cmd_scenes", scenes)
    assert cli.main(["scenes"]) == 130
    assert capsys.readouterr().err.strip() == "testbed: interrupted"


@pytest.mark.slow
def test_workers_print_no_pybullet_banner(tmp_path):
    """A study on workers prints no pybullet build-time banner on stderr: the forkserver
    imported the study's modules, and with them pybullet, unsilenced."""
    out = subprocess.run([sys.executable, "-m", "studies.cli", "study", "fig9", "--quick",
                          "--workers", "2", "--out", str(tmp_path / "f9")], cwd=ROOT,
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert "pybullet build time" not in out.stderr + out.stdout, out.stderr


def test_the_fork_server_ignores_ctrl_c_and_says_nothing_of_a_pool_gone():
    """A review: a Ctrl-C in a study's first seconds printed the fork server's traceback
    (a KeyboardInterrupt inside its preloads, or a starting worker's FileNotFoundError from
    the pool's removed semaphores) after "interrupted". The server's first preload
    (studies._forkserver, run here in a process of its own) ignores SIGINT and keeps that
    one error quiet; any other error of a starting worker is still printed."""
    code = textwrap.dedent("""
        import signal, sys
        import studies._forkserver
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
        ns = {}
        exec(compile("def __setstate__():\\n    raise FileNotFoundError(2, 'gone')\\n",
                     "/usr/lib/python3/multiprocessing/synchronize.py", "exec"), ns)
        for fn in (ns["__setstate__"], lambda: 1 / 0):
            try:
                fn()
            except Exception:
                sys.excepthook(*sys.exc_info())
        """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 0, out.stderr
    assert "FileNotFoundError" not in out.stderr and "ZeroDivisionError" in out.stderr


def test_a_study_interrupted_before_its_report_keeps_its_folder(tmp_path):
    """A review: surfaces stopped by Ctrl-C before its report.md left only trials.sqlite, and
    fig9 then ran in that folder, replaced the results and mixed both studies' trials in the
    database; the first could not resume there. The database now names its study."""
    from studies.common import check_out_folder
    from studies.runner import stored_study

    trials = make_trials("points-lines", 4, _params(3))
    out = tmp_path / "s"
    run_trials(toy_trial, trials, out_dir=out, progress=False, study="surfaces")
    assert stored_study(out) == "surfaces" and not (out / "report.md").exists()
    check_out_folder(out, "surfaces")   # the same study resumes
    # ...also when the study names its scene and seed, as it does since (a folder of before)
    check_out_folder(out, "surfaces", study="surfaces of /s.toml, seed 1")
    with pytest.raises(ValueError, match="holds the trials of 'surfaces'"):
        check_out_folder(out, "fig9", study="fig9 of /s.toml, seed 1")
    with pytest.raises(ValueError, match="holds the trials of 'surfaces' .* not of 'fig9'; "
                                         r"give another folder \(or run testbed study "
                                         r"surfaces with that scene, seed \(without --quick\) "
                                         "with this --out to resume it"):
        check_out_folder(out, "fig9")
    # the advice gives the stored run's --quick (a review was told to add it to resume a
    # run made without it)
    quick = tmp_path / "q"
    run_trials(toy_trial, trials, out_dir=quick, progress=False,
               study="surfaces of /s.toml, seed 1, quick")
    with pytest.raises(ValueError, match="surfaces with that scene, seed and --quick with "):
        check_out_folder(quick, "fig9", study="fig9 of /s.toml, seed 1")
    score = tmp_path / "score"      # a score's owner is no study name: the message says so
    run_trials(toy_trial, trials, out_dir=score, progress=False, study="score m of data")
    with pytest.raises(ValueError, match="run the same testbed score of that dataset with "
                                         "this --out to resume it"):
        check_out_folder(score, "fig9")
    with pytest.raises(ValueError, match="holds the trials of 'surfaces', not of 'fig9'"):
        run_trials(toy_trial, trials, out_dir=out, progress=False, study="fig9")
    again = run_trials(toy_trial, trials, out_dir=out, progress=False, study="surfaces")
    assert again.attrs["skipped"] == 3
    # a database of before (no study recorded) is taken by the study that runs there
    run_trials(toy_trial, trials, out_dir=tmp_path / "old", progress=False)
    assert stored_study(tmp_path / "old") is None
    check_out_folder(tmp_path / "old", "fig9")
    # a folder owned by the bare name is taken by the first run of that study, which owns
    # it from then on (such a folder was open to any scene and seed, a review)
    legacy = tmp_path / "legacy"
    run_trials(toy_trial, trials, out_dir=legacy, progress=False, study="surfaces")
    run_trials(toy_trial, trials, out_dir=legacy, progress=False,
               study="surfaces of /s.toml, seed 1")
    assert stored_study(legacy) == "surfaces of /s.toml, seed 1"
    with pytest.raises(ValueError, match="holds the trials of 'surfaces of /s.toml, seed 1'"):
        check_out_folder(legacy, "surfaces", study="surfaces of /s.toml, seed 2")


def test_a_report_cut_short_does_not_block_the_resume_its_database_names(tmp_path):
    """A review: report.md cut short (a full disk) blocked the resume although
    trials.sqlite names the study, with the advice to give another folder, which loses the
    stored trials. The database's owner decides; a folder of no study's is still refused."""
    from studies.common import check_out_folder

    trials = make_trials("points-lines", 4, _params(2))
    out = tmp_path / "s"
    run_trials(toy_trial, trials, out_dir=out, progress=False, study="fig9 of /s.toml, seed 1")
    for text in ("", "# Stu", "\x00\x00garbage"):
        (out / "report.md").write_text(text)
        check_out_folder(out, "fig9", study="fig9 of /s.toml, seed 1")
        with pytest.raises(ValueError, match="holds the trials of 'fig9 of /s.toml, seed 1'"):
            check_out_folder(out, "fig9", study="fig9 of /s.toml, seed 2")
    # no database: the cut report is no study's, refused as before
    (tmp_path / "r").mkdir()
    (tmp_path / "r" / "report.md").write_text("# Stu")
    with pytest.raises(ValueError, match="holds a report.md that no study wrote"):
        check_out_folder(tmp_path / "r", "fig9")


def test_a_study_is_refused_inside_a_dataset(tmp_path):
    """A review: ``testbed study --out`` inside a dataset folder wrote its results among the
    cases (``testbed score`` refused it). A file of that name that is not ours does not
    count."""
    from studies.common import check_out_folder

    ds = tmp_path / "ds"
    (ds / "case_0000").mkdir(parents=True)
    (ds / "dataset.json").write_text(json.dumps({"generator": "testbed generate",
                                                 "cases": ["case_0000"]}))
    (ds / "case_0000" / "case.json").write_text(json.dumps({"format": "xray-reg-testbed-case"}))
    for out in (ds, ds / "study", ds / "case_0000", ds / "case_0000" / "s"):
        with pytest.raises(ValueError, match=f"--out {out}: inside the dataset of "):
            check_out_folder(out, "fig9")
    assert not (ds / "study").exists()
    check_out_folder(tmp_path / "beside", "fig9")
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "dataset.json").write_text(json.dumps({"name": "my own data"}))
    (mine / "case.json").write_text("not json")
    check_out_folder(mine / "s", "fig9")


def test_an_output_the_study_cannot_replace_is_refused_before_the_work(tmp_path, monkeypatch):
    """A folder named results.csv, or a figure that cannot be written, failed only after the
    whole study had run, with exit 1 and a bare OS message (a review)."""
    from studies.common import check_out_folder

    (tmp_path / "a" / "results.csv").mkdir(parents=True)
    with pytest.raises(ValueError, match="results.csv cannot be replaced \\(it is a folder\\)"):
        check_out_folder(tmp_path / "a", "fig9")
    (tmp_path / "b").mkdir()
    (tmp_path / "b" / "fig9_heatmaps.png").write_bytes(b"")
    real = os.access
    monkeypatch.setattr(os, "access", lambda p, mode: not str(p).endswith(".png")
                        and real(p, mode))   # as for an immutable file (chattr +i)
    with pytest.raises(ValueError, match="fig9_heatmaps.png cannot be replaced \\(not "
                                         "writable\\)"):
        check_out_folder(tmp_path / "b", "fig9")


def test_result_in_slices_returns_the_result_and_times_out_as_result_does(monkeypatch):
    """The study's waits on its workers are sliced so that a signal's Python handler runs
    whichever thread received it (a CI run: SIGCONT after Ctrl-Z left the workers stopped
    while the main thread waited without end); the semantics stay result()'s, with the
    time limit counted from the start the worker reports (or, with none reported, from the
    hand-over plus START_GRACE_S)."""
    import concurrent.futures as cf
    import multiprocessing
    import threading

    import studies.runner as runner
    from studies.runner import SIGNAL_POLL_S, _Deadlines, _result_in_slices

    class Pool:
        trial_starts = multiprocessing.get_context("spawn").SimpleQueue()

    (trial,) = make_trials("points-lines", 0, [{}])
    fut = cf.Future()
    threading.Timer(3 * SIGNAL_POLL_S, fut.set_result, args=(42,)).start()
    deadlines = _Deadlines(Pool(), None)
    deadlines.handed(trial)
    assert _result_in_slices(fut, trial, deadlines) == 42
    limit = 2.5 * SIGNAL_POLL_S
    monkeypatch.setattr(runner, "START_GRACE_S", 2 * SIGNAL_POLL_S)
    for started in (True, False):
        deadlines = _Deadlines(Pool(), limit)
        t0 = time.monotonic()
        deadlines.handed(trial)
        if started:
            Pool.trial_starts.put((trial.key, time.monotonic()))
        with pytest.raises(cf.TimeoutError):
            _result_in_slices(cf.Future(), trial, deadlines)
        due = limit if started else limit + runner.START_GRACE_S
        assert due <= time.monotonic() - t0 < due + 1.0
        assert deadlines.timed_out(trial).error.startswith(
            "TimedOut: the trial still ran" if started else "TimedOut: no worker had started")


def test_code_fingerprint_follows_the_package_source_not_its_place(tmp_path, monkeypatch):
    """A study or score rerun after reglib was edited runs its trials again: the code
    fingerprint follows each ``*.py`` file's bytes, a new file, and not the checkout's
    folder."""
    import shutil
    import sys

    from studies.runner import code_fingerprint

    pkg = tmp_path / "a" / "fpkg"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("X = 1\n")
    (pkg / "sub" / "m.py").write_text("Y = 2\n")
    monkeypatch.syspath_prepend(str(tmp_path / "a"))

    def fp():
        code_fingerprint.cache_clear()
        sys.modules.pop("fpkg", None)
        return code_fingerprint(("fpkg",))

    first = fp()
    assert fp() == first
    (pkg / "sub" / "m.py").write_text("Y = 3\n")
    edited = fp()
    assert edited != first
    (pkg / "sub" / "n.py").write_text("")
    assert fp() != edited
    (pkg / "sub" / "n.py").unlink()
    assert fp() == edited
    # the same files elsewhere: the same fingerprint
    shutil.copytree(pkg, tmp_path / "b" / "fpkg")
    monkeypatch.syspath_prepend(str(tmp_path / "b"))
    assert fp() == edited
    # a package that cannot be found is counted by its name, not an error
    code_fingerprint.cache_clear()
    assert code_fingerprint(("no_such_package_xyz",)) != edited
    code_fingerprint.cache_clear()


def test_a_trial_stored_by_other_code_is_run_again_and_said(tmp_path, capsys):
    from studies.runner import make_trials, run_trials

    trials = make_trials("points-lines", 3, _params(2), fingerprint="code-1")
    run_trials(toy_trial, trials, out_dir=tmp_path, progress=False)
    capsys.readouterr()
    again = make_trials("points-lines", 3, _params(2), fingerprint="code-2")
    df = run_trials(toy_trial, again, out_dir=tmp_path, progress=False)
    err = capsys.readouterr().err
    assert "2 trial(s) stored in" in err and "run again" in err
    assert df.attrs["stale"] == 2 and df.attrs["executed"] == 2
    # the same code again: nothing stale, nothing run
    df = run_trials(toy_trial, again, out_dir=tmp_path, progress=False)
    assert df.attrs["stale"] == 0 and df.attrs["executed"] == 0
    assert "run again" not in capsys.readouterr().err
