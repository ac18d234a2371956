"""Progress of ``closing_the_loop`` and the command line (issue 41 item 2): a line as the baseline and
each round end, each fit's bar named, ``--quiet``, and Ctrl-C stopping the rounds' worker processes."""
import os
import re
import signal
import subprocess
import sys
import time

import pytest

from sfem_filters import cli, resources
from sfem_filters.benchmark import comparison
from sfem_filters.batch import split_timing
from sfem_filters.cardiac import annulus_sequence, closing, sequence
from sfem_filters.cardiac.sequence import save_sequence
from sfem_filters.cardiac.specs import specs_from
from sfem_filters.cli import main

#: the smallest case of tests/cardiac/test_rounds.py with two rounds: two effects to find, 5 frames,
#: 3 smoother iterations, material fixed, no cross-validation (9 folds of 8 landmarks)
KW = dict(candidates=["active_polar", "cavity_pressure", "active_radial"], parameterisation="none", max_rounds=2,
          max_iterations=3, corrections=False, selection="best", max_tries=3, folds=9)
CLI_KW = ["--candidates", "active_polar,cavity_pressure,active_radial", "--parameterisation", "none",
          "--max-iterations", "3", "--folds", "9", "--max-tries", "3"]


def _sequence():
    return annulus_sequence(["active_polar", "cavity_pressure"], amplitude=[(0.15, -0.3), (0.5,)], n_frames=5, seed=1)


@pytest.fixture(scope="module")
def sequence_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("progress") / "two_effects.npz"
    save_sequence(_sequence(), path)
    return str(path)


def test_a_line_as_each_round_ends_and_the_report_unchanged(capsys, monkeypatch):
    """The baseline's and each round's line say what was tried (score, evidence), what was kept, the
    held-out error so far against the spline's (the report's own figures), the elapsed time and,
    while rounds are left, an upper bound of the time left; each fit's bar is named after what it
    fits. Without progress: no line, and the same report to the last figure."""
    seq = _sequence()
    real, names = closing.run, []
    monkeypatch.setattr(closing.workers, "run", lambda *a, **kw: (names.append(kw["name"]), real(*a, **kw))[1])
    out = closing.closing_the_loop(seq, *specs_from(**KW), progress=True)
    monkeypatch.setattr(closing.workers, "run", real)
    err = capsys.readouterr().err
    lines = [ln for ln in re.split(r"[\r\n]", err) if ln.startswith(("baseline (", "round "))
             and (": tried" in ln or "log p(y)" in ln)]
    assert len(lines) == 3, err
    assert err.startswith(f"closing the loop on {seq.n_points} points x {seq.n_frames} frames: mesh and baseline fit, "
                          "then at most 2 rounds\n")
    spline = f"(spline {out.reference['heldout_rmse_px']:.3f} px)"
    base = out.rounds[0]
    assert lines[0].startswith(f"baseline (material fixed): log p(y) {base.log_evidence:.1f} nats")
    assert f"held-out error {base.run.metrics['heldout_rmse_px']:.3f} px {spline}" in lines[0]
    for number, line in enumerate(lines[1:], 1):
        row = next(r for r in out.rounds if r.number == number and r.added)
        assert line.startswith(f"round {number} (") and f"; kept {row.added};" in line
        for t in row.tried:
            assert f"{t['effect']} (score {t['score']:.1f}, evidence {t['evidence_gain']:+.1f} nats)" in line
        latest = [r for r in out.rounds if r.number == number][-1]
        assert f"held-out error {latest.run.metrics['heldout_rmse_px']:.3f} px {spline}" in line
        assert "elapsed " in line
    assert "at most about" in lines[1] and "upper bound: 1 round left x" in lines[1]
    assert "stopped: max_rounds (2) reached" in lines[2] and "upper bound" not in lines[2]
    # each fit is named after what it fits on its progress bar (the smoother's description, which a
    # fit without a material map does not show: no iterations); the runs keep the variants' labels
    assert names[0] == "baseline (material fixed)"
    assert set(names[1:4]) == {f"round 1: + {e}" for e in KW["candidates"]}
    assert "round 2: + active_polar" in names
    assert out.rounds[0].run.name == "none" and out.rounds[1].run.name == out.rounds[1].added
    quiet = closing.closing_the_loop(seq, *specs_from(**KW), progress=False)
    assert capsys.readouterr().err == ""
    assert split_timing(quiet.as_json())[0] == split_timing(out.as_json())[0]


def test_a_round_that_keeps_nothing_says_why_it_stopped(capsys):
    """No candidate is significant and corrections are off: the round's line says it tried nothing
    and why the rounds stopped, with the baseline's held-out error."""
    out = closing.closing_the_loop(annulus_sequence(None, n_frames=4, seed=0),
                                   *specs_from(**{**KW, "max_rounds": 1, "alpha": 1e-12}), progress=True)
    assert out.stop_reason == "no significant candidate"
    line = next(ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("round 1 ("))
    assert "tried nothing" in line and "stopped: no significant candidate" in line
    assert f"held-out error {out.rounds[0].run.metrics['heldout_rmse_px']:.3f} px" in line


@pytest.mark.parametrize("flags, shown", [([], True), (["--quiet"], False), (["-q"], False),
                                          (["--no-progress"], False), (["--quiet", "--no-progress"], False)])
def test_quiet_and_no_progress_reach_every_verb(monkeypatch, flags, shown):
    seen = {}

    def fake(*args, **kw):
        seen["progress"] = kw["progress"]
        raise SystemExit(0)

    monkeypatch.setattr(closing, "closing_the_loop", fake)
    monkeypatch.setattr(sequence, "load_sequence", lambda path: None)
    with pytest.raises(SystemExit):
        main(["dense", "x.npz", *flags])
    assert seen.pop("progress") is shown
    monkeypatch.setattr(comparison, "run_comparison", fake)
    with pytest.raises(SystemExit):
        main(["compare", *flags])
    assert seen.pop("progress") is shown
    observe = [f for f in flags if f != "--no-progress"]
    assert cli.build_parser().parse_args(["observe", "x.npz", "--out", "y.npz", *observe]).quiet is bool(observe)


def test_dense_quiet_prints_the_report_and_no_progress(sequence_file, capsys):
    assert main(["dense", sequence_file, *CLI_KW, "--max-rounds", "1", "--quiet", "--workers", "1"]) == 0
    got = capsys.readouterr()
    assert "held-out" in got.out                        # the report
    assert "baseline (" not in got.err and "round 1" not in got.err and "\r" not in got.err, got.err


@pytest.mark.parametrize("wait", [0.2, 1.5])
def test_ctrl_c_stops_the_workers_and_says_what_finished(sequence_file, wait):
    """Ctrl-C (SIGINT to the whole process group, as a terminal sends it) while a round's fits start
    or run in two worker processes: exit code 130, one line saying what had finished and that
    nothing is kept, no worker's traceback and no leaked semaphores (the pool shut down)."""
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
    proc = subprocess.Popen([sys.executable, "-m", "sfem_filters.cli", "dense", sequence_file, *CLI_KW,
                             "--max-rounds", "3", "--max-iterations", "20", "--workers", "2"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env, text=True, bufsize=1,
                            start_new_session=True)
    lines, deadline = [], time.monotonic() + 120
    try:
        while time.monotonic() < deadline:            # until the round's fits are handed to the workers
            line = proc.stderr.readline()
            if not line:
                break
            lines.append(line)
            if "worker processes" in line:
                break
        assert any("worker processes" in ln for ln in lines), "".join(lines)
        time.sleep(wait)                                # the workers start (0.2 s) or run their fits
        os.killpg(proc.pid, signal.SIGINT)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    err = "".join(lines) + err
    assert proc.returncode == 130, err
    message = [ln for ln in err.splitlines() if ln.startswith("sfem-filters dense: interrupted: ")]
    assert len(message) == 1, err
    assert "after the baseline" in message[0] and "nothing is kept" in message[0]
    assert "leaked semaphore" not in err and "Traceback" not in err, err


def test_workers_start_with_ctrl_c_ignored_and_the_handler_comes_back():
    before = signal.getsignal(signal.SIGINT)
    with resources.starting_workers():
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    assert signal.getsignal(signal.SIGINT) is before


def test_an_interrupted_compare_says_where_its_checkpoints_are(monkeypatch, capsys, tmp_path):
    def interrupted(*args, **kw):
        raise KeyboardInterrupt

    monkeypatch.setattr(comparison, "run_comparison", interrupted)
    assert main(["compare", "--quiet"]) == 130
    assert capsys.readouterr().err == ("sfem-filters compare: interrupted: nothing is kept (--checkpoint-dir DIR keeps "
                                       "the joint estimators' progress)\n")
    assert main(["compare", "--checkpoint-dir", str(tmp_path)]) == 130
    assert capsys.readouterr().err == (f"sfem-filters compare: interrupted: the joint estimators' checkpoints are kept "
                                       f"in {tmp_path} (the same command resumes from them)\n")
