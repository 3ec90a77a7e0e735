"""Sums a test profile (``PATEXGS_TEST_PROFILE=FILE``, see tests/conftest.py) per test file:
``python tests/profile_summary.py FILE [PREFIX] [--tests N]`` prints each file's wall time and the
seconds of it spent tracing, lowering, compiling and loading from the persistent cache, and what is
left (running programs, Python, subprocesses); with ``--tests N``, the N slowest tests as well."""

from __future__ import annotations

import argparse
import collections
import json

KINDS = ("trace", "lower", "compile", "load")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("file")
    ap.add_argument("prefix", nargs="?", default="", help="only tests whose node id starts with this")
    ap.add_argument("--tests", type=int, default=0, help="also list the N slowest tests")
    args = ap.parse_args(argv)
    recs = [json.loads(line) for line in open(args.file) if line.strip()]
    recs = [r for r in recs if r["test"].startswith(args.prefix)]
    per: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
    for r in recs:
        c = per[r["test"].split("::")[0]]
        c["wall"] += r["wall"]
        c["compiles"] += r.get("compiles", 0)
        for k in KINDS:
            c[k] += r.get(k, 0.0)
    total = collections.Counter()
    for c in per.values():
        total.update(c)
    print(f"{'wall s':>8} {'trace':>7} {'lower':>7} {'compile':>8} {'(n)':>6} {'load':>6} {'rest':>7}  file")
    for name, c in sorted(per.items(), key=lambda x: -x[1]["wall"]) + [("all", total)]:
        rest = c["wall"] - sum(c[k] for k in KINDS)
        print(f"{c['wall']:8.1f} {c['trace']:7.1f} {c['lower']:7.1f} {c['compile']:8.1f} {c['compiles']:6d} "
              f"{c['load']:6.1f} {rest:7.1f}  {name}")
    for r in sorted(recs, key=lambda r: -r["wall"])[:args.tests]:
        print(f"{r['wall']:8.1f} compile {r.get('compile', 0.0):6.1f} ({r.get('compiles', 0)})  {r['test']}")


if __name__ == "__main__":
    main()
