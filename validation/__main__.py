"""``python -m validation list | run NAME... | run --all | render NAME... | sync-readme`` (from the repository root).

``run`` and ``render`` into ``docs/_generated/`` also rewrite its table of claims
(:func:`validation.claims_index.write_claims_table`: each claim's last full run, from its stored provenance)."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from . import CLAIMS, claim
from ._core import GENERATED, command_line, render_claim, run_claim
from .claims_index import last_full_run, write_claims_table
from .readme import sync


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="python -m validation", description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="verb", required=True)
    sub.add_parser("list", help="the claims, their titles and the cost of each tier")
    run = sub.add_parser("run", help="run claims and write <out>/<name>.json and .md")
    run.add_argument("names", nargs="*", metavar="NAME", help=f"claims: {', '.join(CLAIMS)}")
    run.add_argument("--all", action="store_true", help="every claim, one after the other")
    tier = run.add_mutually_exclusive_group()
    tier.add_argument("--quick", dest="tier", action="store_const", const="quick",
                      help="the quick tier (seconds to a minute; what the test suite runs)")
    tier.add_argument("--full", dest="tier", action="store_const", const="full",
                      help="the full tier (default): the numbers the docs show")
    run.add_argument("--out", type=Path, default=None,
                     help=f"output folder (default {GENERATED.relative_to(GENERATED.parent.parent)} for the full "
                          "tier; the quick tier needs --out, so it never overwrites the committed outputs)")
    render = sub.add_parser("render", help="rewrite <out>/<name>.md from the stored <name>.json with the claim's "
                                           "current table (no run: the stored numbers and their provenance)")
    render.add_argument("names", nargs="+", metavar="NAME", help=f"claims: {', '.join(CLAIMS)}")
    render.add_argument("--out", type=Path, default=GENERATED, help="folder of the stored JSON (default "
                        f"{GENERATED.relative_to(GENERATED.parent.parent)})")
    sub.add_parser("sync-readme", help="rewrite README.md's generated blocks from their files")
    return ap


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    if args.verb == "list":
        for name in CLAIMS:
            mod = claim(name)
            last = last_full_run(name)
            cost = f"last full run {last}" if last else f"full tier not run here; estimated {mod.FULL_COST}"
            print(f"{name:<21}{mod.TITLE}  ({cost})")
        return 0
    if args.verb == "sync-readme":
        changed = sync()
        print("\n".join(f"rewrote {c}" for c in changed) or "README.md is up to date")
        return 0
    if args.verb == "render":
        unknown = [n for n in args.names if n not in CLAIMS]
        if unknown:
            build_parser().error(f"render: unknown claims {unknown}; expected names from {list(CLAIMS)}")
        for name in args.names:
            if not (args.out / f"{name}.json").is_file():
                build_parser().error(f"render: no stored results {args.out / (name + '.json')}; run the claim first")
            render_claim(claim(name), args.out, command_line(argv))
            print(f"{name}: rewrote {args.out / (name + '.md')} from its stored results")
        if Path(args.out).resolve() == GENERATED.resolve():
            print(f"rewrote {write_claims_table(args.out)}")
        return 0
    tier = args.tier or "full"
    names = list(CLAIMS) if args.all else args.names
    if not names:
        build_parser().error("run: name a claim or give --all")
    unknown = [n for n in names if n not in CLAIMS]
    if unknown:
        build_parser().error(f"run: unknown claims {unknown}; expected names from {list(CLAIMS)}")
    if args.out is None and tier == "quick":
        build_parser().error("run --quick: give --out DIR (the quick tier never writes over docs/_generated/)")
    out = args.out or GENERATED
    failed = []
    try:
        for name in names:
            mod = claim(name)
            print(f"{name}: {tier} tier ...", flush=True)
            payload = run_claim(mod, tier, out, command_line(argv))
            problems = mod.check(payload["results"], tier)
            print(f"{name}: wrote {out / (name + '.json')} and .md in {payload['provenance']['wall_seconds']:.1f} s",
                  flush=True)
            for p in problems:
                print(f"{name}: implausible: {p}", file=sys.stderr)
            failed += [name] if problems else []
    finally:                                      # the claims run before a failing one are in the index too
        if Path(out).resolve() == GENERATED.resolve():
            print(f"rewrote {write_claims_table(out)}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
