"""Every product benchmark in benchmarks/ runs, at its smallest setting, as a user would run it.

Each script is run as a subprocess (``python benchmarks/NAME.py ...``): it must exit 0 and print
its table, so a rename of a public name breaks this test rather than the script. The scripts use
only public names of :mod:`sfem_filters`; :func:`test_benchmarks_use_only_public_names` checks it.
"""
from __future__ import annotations

import ast
import importlib
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
BENCHMARKS = ROOT / "benchmarks"
#: Script -> (its smallest arguments, a line its output must hold).
SMALLEST = {
    "batch.py": (["--seeds", "0-1", "--workers", "1"], "per-job result files identical byte for byte: 2/2"),
    "smoother_memory.py": (["--subject", "annulus", "--frames", "6", "--repeat", "1", "--maps", "region",
                            "--every", "3"], "region   every 3"),
    "rounds_parallel.py": (["--subject", "annulus", "--frames", "6", "--max-iterations", "1", "--max-rounds", "1"],
                           "rounds: the two reports identical but for wall times: True"),
    "blas_threads.py": (["--quick"], ""),
    "frame_threads.py": (["--subject", "annulus", "--frames", "6", "--max-iterations", "2"],
                         "baseline fit: the two reports identical but for wall times: True"),
}


def test_every_benchmark_has_a_smoke_setting():
    assert sorted(p.name for p in BENCHMARKS.glob("*.py")) == sorted(SMALLEST)


@pytest.mark.parametrize("script", sorted(SMALLEST))
def test_benchmark_runs_at_its_smallest_setting(script, tmp_path):
    args, expected = SMALLEST[script]
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "MPLBACKEND": "Agg"}
    proc = subprocess.run([sys.executable, str(BENCHMARKS / script), *args], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-4000:]
    assert expected in proc.stdout


def _public(module: str) -> set:
    return set(getattr(importlib.import_module(module), "__all__", ()))


def _is_public_module(name: str) -> bool:
    try:
        importlib.import_module(name)
    except ImportError:
        return False
    return not any(part.startswith("_") for part in name.split("."))


@pytest.mark.parametrize("script", sorted(SMALLEST))
def test_benchmarks_use_only_public_names(script):
    """Every name a script imports from sfem_filters is in its module's ``__all__``, and no
    attribute starting with an underscore is read off anything."""
    tree = ast.parse((BENCHMARKS / script).read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("sfem_filters"):
            assert not any(part.startswith("_") for part in node.module.split(".")), node.module
            public = _public(node.module)
            for alias in node.names:
                assert alias.name in public or _is_public_module(f"{node.module}.{alias.name}"), \
                    f"{script}: {alias.name} is not public in {node.module}"
        if isinstance(node, ast.Attribute):
            assert not (node.attr.startswith("_") and not node.attr.startswith("__")), \
                f"{script}:{node.lineno}: private attribute {node.attr}"
