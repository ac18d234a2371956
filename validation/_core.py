"""What every claim shares: its provenance, its output files and how it is run.

A claim module defines ``NAME``, ``TITLE``, ``TIERS`` (``{"quick": settings, "full": settings}``,
small dicts of JSON values), ``compute(settings) -> dict`` (the results, JSON values only),
``markdown(results) -> str`` (the rendered table), ``check(results, tier) -> list`` (the
plausibility problems found; empty when the results are plausible) and ``TOLERANCES`` (how far
a fresh full run may move from the stored one, used by :func:`compare`). This module runs it:
times the computation, gathers the provenance and writes ``<out>/<name>.json`` and
``<out>/<name>.md``.
"""
from __future__ import annotations

import datetime
import json
import math
import os
import platform
import resource
import subprocess
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
GENERATED = ROOT / "docs" / "_generated"
TIER_NAMES = ("quick", "full")
PROVENANCE_KEYS = ("package_version", "git_commit", "git_dirty", "date_utc", "cpu_model", "blas_threads",
                   "command", "wall_seconds", "tier")


def _git(*args, root: Path = ROOT) -> str | None:
    try:
        out = subprocess.run(["git", *args], cwd=root, capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() if out.returncode == 0 else None


def cpu_model() -> str:
    """The CPU's model name from ``/proc/cpuinfo``, else what :mod:`platform` says."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown"


def blas_threads() -> int | None:
    """The largest thread count of the BLAS libraries loaded in this process (threadpoolctl)."""
    from threadpoolctl import threadpool_info
    counts = [p.get("num_threads") for p in threadpool_info() if p.get("user_api") == "blas"]
    return max(counts) if counts else None


#: ``ru_maxrss`` is in kibibytes on Linux (``getrusage(2)``); the tables print decimal GB (1e9 bytes).
RU_MAXRSS_BYTES = 1024
MIB = 2 ** 20


def peak_rss_bytes(who: str = "self") -> int:
    """Peak resident memory in bytes of this process (``who="self"``) or of its largest waited-for child
    (``"children"``), from ``ru_maxrss``."""
    which = {"self": resource.RUSAGE_SELF, "children": resource.RUSAGE_CHILDREN}
    if who not in which:
        raise ValueError(f"who: expected 'self' or 'children', got {who!r}")
    return resource.getrusage(which[who]).ru_maxrss * RU_MAXRSS_BYTES


def mib_to_gb(mib: float) -> float:
    """Mebibytes (2**20 bytes, what the claims store as ``peak_rss_mb``) to decimal gigabytes (1e9 bytes)."""
    return mib * MIB / 1e9


def code_state(root: Path = ROOT) -> dict:
    """The git commit and whether the tracked files of the clone at ``root`` differ from it (``None`` outside one).

    The suite's own outputs (``docs/_generated``) do not count: a claim rewrites its files during
    its run, and claims run side by side rewrite theirs, so counting them would mark every such
    run as made from uncommitted code when the code was the commit's.
    """
    status = _git("status", "--porcelain", "--untracked-files=no", "--", ".",
                  f":(exclude){GENERATED.relative_to(ROOT).as_posix()}", root=root)
    return {"git_commit": _git("rev-parse", "HEAD", root=root), "git_dirty": None if status is None else bool(status)}


def provenance(tier: str, command: str, wall_seconds: float, start: dict | None = None) -> dict:
    """Package version, git commit and whether the tree had uncommitted changes (as at the run's
    ``start``, a :func:`code_state`; ``git_changed_during_run`` when the commit or the tree was not
    the same at its end), date (UTC), CPU, BLAS threads, the machine's load at the end (1, 5 and
    15 min: other jobs slow the timings), the command line, wall time (s) and tier of one run."""
    import sfem_filters
    end = code_state()
    start = end if start is None else start
    return {"package_version": sfem_filters.__version__,
            "git_commit": start["git_commit"],
            "git_dirty": start["git_dirty"],
            "git_changed_during_run": end != start,
            "date_utc": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
            "cpu_model": cpu_model(),
            "blas_threads": blas_threads(),
            "cpu_count": os.cpu_count(),
            "load_average": [round(x, 2) for x in os.getloadavg()],
            "python": platform.python_version(),
            "data_dir": os.environ.get("SFEM_FILTERS_DATA"),
            "command": command,
            "wall_seconds": round(float(wall_seconds), 1),
            "tier": tier}


def json_safe(value):
    """``value`` with numpy numbers and arrays as Python ones and every non-finite float as ``None``."""
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, np.ndarray):
        return json_safe(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def header(prov: dict) -> str:
    """The provenance line written above every generated table (Markdown)."""
    commit = (prov["git_commit"] or "unknown")[:10]
    dirty = " with uncommitted changes" if prov["git_dirty"] else ""
    if prov.get("git_changed_during_run"):
        dirty += " (the tree changed during the run)"
    threads = prov["blas_threads"]
    return (f"*Generated by `{prov['command']}` ({prov['tier']} tier) in {prov['wall_seconds']:.0f} s on "
            f"{prov['date_utc']}: sfem_filters {prov['package_version']}, commit {commit}{dirty}, "
            f"{prov['cpu_model']}, {threads if threads is not None else '?'} BLAS "
            f"thread{'' if threads == 1 else 's'}, load average {prov['load_average'][0]:.1f} on "
            f"{prov['cpu_count']} cores.*")


def md_table(columns, rows) -> str:
    """A Markdown table: ``columns`` the header cells, ``rows`` lists of cells (str)."""
    lines = ["| " + " | ".join(columns) + " |", "|" + "|".join("---" for _ in columns) + "|"]
    lines += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join(lines)


def fmt(x, spec: str) -> str:
    """``x`` formatted with ``spec``, or ``-`` where it is missing or not finite."""
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    return format(x, spec)


def run_claim(module, tier: str, out_dir, command: str) -> dict:
    """Run ``module``'s ``tier``, write ``<out_dir>/<NAME>.json`` and ``.md``; return the JSON payload."""
    if tier not in TIER_NAMES:
        raise ValueError(f"tier: expected one of {TIER_NAMES}, got {tier!r}")
    settings = module.TIERS[tier]
    Path(out_dir).mkdir(parents=True, exist_ok=True)
    start = code_state()                # the code the run starts from (a long run may outlive a commit)
    t0 = time.perf_counter()
    results = json_safe(module.compute(dict(settings), out_dir=Path(out_dir)))
    wall = time.perf_counter() - t0
    prov = provenance(tier, command, wall, start)
    payload = {"claim": module.NAME, "title": module.TITLE, "provenance": prov, "settings": json_safe(settings),
               "results": results}
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    with open(out_dir / f"{module.NAME}.json", "w") as f:
        json.dump(payload, f, indent=2, allow_nan=False)
        f.write("\n")
    _write_markdown(module, out_dir, header(prov) + "\n\n", results)
    return payload


def _write_markdown(module, out_dir, head: str, results: dict) -> None:
    """``<NAME>.md`` from ``module.markdown``, and ``<NAME>_<part>.md`` from each of ``module.EXTRA_MARKDOWN``
    (``{part: function of the results}``, e.g. a short summary the README shows), each under ``head``."""
    parts = {"": module.markdown, **{f"_{k}": v for k, v in getattr(module, "EXTRA_MARKDOWN", {}).items()}}
    for suffix, make in parts.items():
        with open(Path(out_dir) / f"{module.NAME}{suffix}.md", "w") as f:
            f.write(head + make(results).rstrip() + "\n")


def render_claim(module, out_dir, command: str) -> dict:
    """Rewrite ``<out_dir>/<NAME>.md`` from the stored ``<NAME>.json`` with the claim's current
    ``markdown`` (no run): a change of presentation, the numbers and their provenance those of the
    stored run, the header saying so. Returns the stored payload."""
    payload = load(module.NAME, out_dir)
    code = code_state()
    commit = (code.get("git_commit") or "unknown")[:10]
    note = (f"*Table rendered from that run's stored results by `{command}` at commit {commit}"
            f"{' with uncommitted changes' if code.get('git_dirty') else ''}.*")
    _write_markdown(module, out_dir, header(payload["provenance"]) + "\n" + note + "\n\n", payload["results"])
    return payload


def load(name: str, out_dir=GENERATED) -> dict:
    """The stored JSON of claim ``name`` in ``out_dir``."""
    with open(Path(out_dir) / f"{name}.json") as f:
        return json.load(f)


def finite_numbers(value, path="results"):
    """Paths of every number in ``value`` that is not finite (``None`` stands for one)."""
    bad = []
    if isinstance(value, dict):
        for k, v in value.items():
            bad += finite_numbers(v, f"{path}.{k}")
    elif isinstance(value, list):
        for i, v in enumerate(value):
            bad += finite_numbers(v, f"{path}[{i}]")
    elif isinstance(value, float) and not math.isfinite(value):
        bad.append(path)
    return bad


def compare(stored, fresh, tolerances: dict, path="results") -> list:
    """Differences between two results beyond ``tolerances``: ``{key: (rtol, atol)}`` for the
    numbers under a key of that name (the key ``"*"`` for every other number); a key whose
    tolerance is ``None`` is not compared (timings). Strings, ints and booleans must be equal."""
    out = []
    if isinstance(stored, dict) and isinstance(fresh, dict):
        if set(stored) != set(fresh):
            return [f"{path}: keys {sorted(set(stored) ^ set(fresh))} in one run only"]
        for k in stored:
            tol = tolerances.get(k, tolerances.get("*", (0.0, 0.0)))
            if tol is None:
                continue
            out += compare(stored[k], fresh[k], {**tolerances, "*": tol}, f"{path}.{k}")
        return out
    if isinstance(stored, list) and isinstance(fresh, list):
        if len(stored) != len(fresh):
            return [f"{path}: {len(stored)} entries stored, {len(fresh)} now"]
        for i, (a, b) in enumerate(zip(stored, fresh)):
            out += compare(a, b, tolerances, f"{path}[{i}]")
        return out
    if isinstance(stored, float) or isinstance(fresh, float):
        if stored is None or fresh is None:
            return [] if stored is fresh else [f"{path}: {stored} stored, {fresh} now"]
        rtol, atol = tolerances.get("*", (0.0, 0.0))
        if abs(stored - fresh) > atol + rtol * abs(stored):
            out.append(f"{path}: {stored} stored, {fresh} now (rtol {rtol}, atol {atol})")
        return out
    if stored != fresh:
        out.append(f"{path}: {stored!r} stored, {fresh!r} now")
    return out


def command_line(argv) -> str:
    """The command as typed from the repository root."""
    return "python -m validation " + " ".join(argv)

