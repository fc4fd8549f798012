#!/usr/bin/env python3
"""`make fuzz`: the fuzz tests (test/unit/test_fuzz_*.py) with many more examples.

Runs pytest once over every ``test_fuzz_*.py`` (and the node-callback fuzz in
test_node_bad_input.py) with ``FUZZ_EXAMPLES`` examples per test (default
2000; CI runs 40), Hypothesis's random exploration with a FIXED seed (``--seed``, so a run is
reproducible and a failure can be replayed), and prints per test: examples tried, failing
examples, seconds. The figures go to ``results/fuzz/fuzz.json`` and, as a markdown table, to
stdout (copied into docs/reliability.md).

Usage: tools/fuzz.py [--examples N] [--seed S] [--only SUBSTRING]
"""
from __future__ import annotations

import argparse
import datetime
import glob
import json
import os
import re
import subprocess
import sys
import time

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), ".."))


def parse_statistics(text: str) -> dict:
    """Hypothesis's ``--hypothesis-show-statistics`` output -> {test id: {examples, failing, seconds}}."""
    out: dict = {}
    current = None
    for line in text.splitlines():
        m = re.match(r"^(test/\S+::\S+):\s*$", line.strip())
        if m:
            current = m.group(1)
            out[current] = {"examples": 0, "failing": 0, "invalid": 0, "seconds": 0.0}
            continue
        if current is None:
            continue
        m = re.search(r"during \w+ phase \(([\d.]+) seconds\)", line)
        if m:
            out[current]["seconds"] += float(m.group(1))
        m = re.search(r"(\d+) passing(?: examples)?, (\d+) failing(?: examples)?,? (?:and )?(\d+) invalid", line)
        if m:
            out[current]["examples"] += int(m.group(1)) + int(m.group(2))
            out[current]["failing"] += int(m.group(2))
            out[current]["invalid"] += int(m.group(3))
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--examples", type=int, default=int(os.environ.get("FUZZ_EXAMPLES", "2000")),
                        help="examples per fuzz test (default 2000)")
    parser.add_argument("--seed", type=int, default=20261122, help="Hypothesis seed (default 20261122)")
    parser.add_argument("--only", default="", help="pytest -k expression")
    args = parser.parse_args(argv)

    files = sorted(os.path.relpath(f, REPO) for f in glob.glob(os.path.join(REPO, "test", "unit", "test_fuzz_*.py")))
    # the node callbacks' fuzz lives with the node bad-input tests (it needs rospy: skipped without)
    files.append(os.path.join("test", "unit", "test_node_bad_input.py"))
    env = dict(os.environ, FUZZ_EXAMPLES=str(args.examples), HYPOTHESIS_PROFILE="dev")
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-W", "ignore::RuntimeWarning",
           "--hypothesis-show-statistics", f"--hypothesis-seed={args.seed}", *files]
    cmd += ["-k", f"fuzz and ({args.only})" if args.only else "fuzz"]
    print(f"fuzz: {args.examples} examples per test, seed {args.seed}: {' '.join(files)}", flush=True)
    t0 = time.time()
    proc = subprocess.run(cmd, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    wall = time.time() - t0
    stats = parse_statistics(proc.stdout)
    summary = [line for line in proc.stdout.splitlines() if re.search(r"\d+ (passed|failed)", line)]
    failed = [line.split()[1] for line in proc.stdout.splitlines() if line.startswith("FAILED ")]
    if proc.returncode != 0:
        print(proc.stdout[-20000:])

    rows = ["| fuzz test | examples tried | failing | s |", "|---|---:|---:|---:|"]
    total = fails = 0
    for test, s in sorted(stats.items()):
        name = test.split("::")[-1]
        bad = s["failing"] or any(test.endswith(f.split("::")[-1]) for f in failed)
        rows.append(f"| `{name}` | {s['examples']} | {s['failing']}{' (FAILED)' if bad else ''} | {s['seconds']:.1f} |")
        total += s["examples"]
        fails += s["failing"]
    rows.append(f"| **total** ({len(stats)} tests) | **{total}** | **{fails}** | {wall:.0f} (wall) |")
    table = "\n".join(rows)
    print(table)
    print(summary[-1] if summary else "no pytest summary line")

    os.makedirs(os.path.join(REPO, "results", "fuzz"), exist_ok=True)
    with open(os.path.join(REPO, "results", "fuzz", "fuzz.json"), "w") as handle:
        json.dump({"date": datetime.datetime.utcnow().strftime("%Y-%m-%dT%H:%M:%SZ"), "seed": args.seed,
                   "examples_per_test": args.examples, "wall_seconds": wall, "tests": stats,
                   "failed_tests": failed, "pytest_exit": proc.returncode, "markdown": table}, handle, indent=1)
    return proc.returncode


if __name__ == "__main__":
    sys.exit(main())
