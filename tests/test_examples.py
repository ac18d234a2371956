"""Every script in examples/ runs, and the numbers the README quotes from it are what it prints.

The default suite runs each example with a small setting where the full one is slow; the
``slow`` tests run the full setting and check the README's figures against the script's output.
"""
import os
import pathlib
import re
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"
# The README and the docs' frozen results (docs/frozen/), whitespace-insensitive: the numbers they quote
QUOTING = [ROOT / "README.md", *sorted((ROOT / "docs" / "frozen").glob("*.md"))]
README = " ".join(" ".join(p.read_text() for p in QUOTING).split())
TESTED = {"synthetic_comparison.py", "dense_closing_the_loop.py", "front_end_subject_a.py"}


def run_example(name: str, *args: str, timeout: int = 1800) -> str:
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    proc = subprocess.run([sys.executable, str(EXAMPLES / name), *args], capture_output=True, text=True,
                          timeout=timeout, env=env, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc.stdout


def numbers(pattern: str, text: str) -> tuple:
    match = re.search(pattern, text)
    assert match, f"{pattern!r} not in the output:\n{text[-3000:]}"
    return match.groups()


def test_every_example_is_covered():
    assert {p.name for p in EXAMPLES.glob("*.py")} == TESTED


def test_synthetic_comparison_prints_the_readme_table_of_seed_0():
    out = run_example("synthetic_comparison.py")
    for strategy, label in (("uniform_kf", "KF, uniform material"), ("perfect_kf", "KF, perfect material"),
                            ("joint_ekf", "joint EKF")):
        (D,) = numbers(rf"{strategy}\s+loops=\d+\s+KS D=([0-9.]+)", out)
        assert re.search(rf"\| 0 \| {re.escape(label)} \| {re.escape(D)} \|", README), (strategy, D)   # table1


@pytest.mark.needs_data("subject_a")
@pytest.mark.slow                      # 75 s: the default suite keeps under 10 minutes
def test_front_end_tracking_numbers_are_the_readmes():
    """Parts 1-2 (tracking error and confidence) do not depend on the loop count: the quick run
    prints the README's figures; part 3 (fusion) is checked in the slow test."""
    out = run_example("front_end_subject_a.py", "--max-iterations", "1")
    rmse, normal, tangential = numbers(r"RMSE ([0-9.]+) px \(normal ([0-9.]+), tangential ([0-9.]+)\)", out)
    assert f"| tracking error | {rmse} (normal to the border {normal}, along it {tangential}) |" in README
    motion = numbers(r"DENSE motion of those points: RMS ([0-9.]+) px \(normal ([0-9.]+), tangential ([0-9.]+)\)", out)
    assert "| DENSE motion of the same points | {} (normal {}, along {}) |".format(*motion) in README
    rho_step, rho_acc = numbers(r"rho\(1 - c, error of that step\) = ([0-9.]+).*rho\(accumulated sigma, error\) = "
                                r"([0-9.]+)", out)
    assert f"Spearman rho between `1 - c` and the error of the same step: {float(rho_step):.2f}" in README
    assert f"between the accumulated `sigma` and the accumulated error: {float(rho_acc):.2f}" in README
    assert "tracked borders alone" in out and "mid-wall points: RMSE" in out


@pytest.mark.needs_data("subject_a")
@pytest.mark.slow
def test_front_end_fusion_numbers_are_the_readmes():
    out = run_example("front_end_subject_a.py")
    alone = numbers(r"tracked borders alone\s*: RMSE ([0-9.]+) px, NIS/dof ([0-9.]+)", out)
    both = numbers(r"\+ velocity at (\d+) mid-wall points: RMSE ([0-9.]+) px, NIS/dof ([0-9.]+)", out)
    assert "| tracked borders alone | {} | {} |".format(*alone) in README
    assert "| tracked borders + velocity at {} mid-wall points | {} | {} |".format(*both) in README


@pytest.mark.needs_data("subject_a")
def test_dense_closing_the_loop_runs_quickly():
    out = run_example("dense_closing_the_loop.py", "--quick")
    assert "ranking of candidate effects" in out
    rmse = [float(v) for v in re.findall(r"points held out by both: ([0-9.]+) px", out)]
    assert len(rmse) == 2 and all(0 < v < 5 for v in rmse)


@pytest.mark.needs_data("subject_a")
@pytest.mark.slow
def test_dense_closing_the_loop_numbers_are_the_readmes():
    out = run_example("dense_closing_the_loop.py")
    (n, boundary), (_, midwall) = re.findall(r"RMSE on the (\d+) points held out by both: ([0-9.]+) px", out)
    assert (f"On the {n} points that both configurations hold out, the extended model predicts {boundary} px from "
            f"the boundary landmarks and {midwall} px") in README
