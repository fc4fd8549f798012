#!/usr/bin/env python3
"""Run every benchmark under bench/ and write the figures down.

Each ``bench/bench_<area>.py`` defines ``run(quick: bool) -> dict`` returning
``{"results": {name: number}, "markdown": "section text"}``. This script runs them (all, or the
ones named with ``--only``), merges the numbers into ``results/bench/results.json`` (a flat JSON
object of named numbers) and writes ``docs/benchmarks.md`` with the machine, the date and the
versions of what was measured. A benchmark that fails is reported in both files and makes the
exit code 1; the others still run. Notes written into a section by hand (a branch's measurement,
why a figure moved) go between ``<!-- kept -->`` and ``<!-- /kept -->``: a rerun of the section
carries them over (before its "ran in" line); everything else in it is replaced.

Usage: ``python bench/run.py [--quick] [--only detector,mapping]``
"""
from __future__ import annotations

import argparse
import datetime
import importlib.util
import json
import os
import platform
import sys
import time
import traceback
from typing import Dict, List

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)


def machine_description() -> List[str]:
    """Lines naming the machine, the date and the library versions."""
    import cv2
    import numpy
    import scipy

    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as handle:
            for line in handle:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    mem = ""
    try:
        with open("/proc/meminfo", encoding="utf-8") as handle:
            kb = int(handle.readline().split()[1])
            mem = f", {kb / 1024 / 1024:.0f} GiB RAM"
    except (OSError, ValueError, IndexError):
        pass
    return [
        f"- Date: {datetime.datetime.now(datetime.timezone.utc).strftime('%Y-%m-%d %H:%M UTC')}",
        f"- Machine: {cpu}, {os.cpu_count()} cores{mem}, {platform.system()} {platform.release()}",
        f"- Python {platform.python_version()}, NumPy {numpy.__version__}, OpenCV {cv2.__version__}, "
        f"SciPy {scipy.__version__}",
    ]


def discover() -> Dict[str, str]:
    """Benchmark name -> file path, for every bench/bench_*.py."""
    out = {}
    for name in sorted(os.listdir(HERE)):
        if name.startswith("bench_") and name.endswith(".py"):
            out[name[len("bench_"):-3]] = os.path.join(HERE, name)
    return out


def run_one(name: str, path: str, quick: bool) -> dict:
    spec = importlib.util.spec_from_file_location(f"bench_{name}", path)
    module = importlib.util.module_from_spec(spec)
    assert spec.loader is not None
    spec.loader.exec_module(module)
    out = module.run(quick=quick)
    if not isinstance(out, dict) or not isinstance(out.get("results"), dict):
        raise TypeError(f"bench_{name}.run() must return {{'results': {{...}}, 'markdown': '...'}}")
    return out


def _split_sections(text: str) -> List[str]:
    """The doc's parts: the header, then one string per '## ' section."""
    parts: List[str] = []
    for line in text.splitlines(keepends=True):
        if line.startswith("## ") or not parts:
            parts.append(line)
        else:
            parts[-1] += line
    return parts


KEPT_OPEN = "<!-- kept -->"
KEPT_CLOSE = "<!-- /kept -->"


def kept_blocks(section: str) -> List[str]:
    """The hand-written parts of a section: each ``<!-- kept -->`` ... ``<!-- /kept -->`` block
    (markers included), in order. A block left open runs to the section's end."""
    blocks: List[str] = []
    start = section.find(KEPT_OPEN)
    while start >= 0:
        end = section.find(KEPT_CLOSE, start)
        end = len(section) if end < 0 else end + len(KEPT_CLOSE)
        blocks.append(section[start:end].strip())
        start = section.find(KEPT_OPEN, end)
    return blocks


def with_kept(new: str, old: str) -> str:
    """``new`` (a section just rendered) with the kept blocks of ``old`` (the same section in the
    doc) that it does not hold, put before its ``_(ran in ...)_`` line (or at its end)."""
    blocks = [b for b in kept_blocks(old) if b not in new]
    if not blocks:
        return new
    body = new.rstrip()
    tail = ""
    last = body.rfind("\n_(ran in ")
    if last >= 0:
        body, tail = body[:last].rstrip(), body[last:]
    return body + "\n\n" + "\n\n".join(blocks) + ("\n" + tail if tail else "") + "\n"


def merge_doc(path: str, sections: List[str], run_lines: List[str], names: List[str]) -> str:
    """With --only: the existing doc with the sections just run replaced (same '## ' title) or
    appended, and a header line saying which sections were rerun when, on what. What the old
    section held between ``<!-- kept -->`` and ``<!-- /kept -->`` (notes written by hand: why a
    figure moved, measurements of a branch) is carried over into the new one."""
    with open(path, encoding="utf-8") as handle:
        parts = _split_sections(handle.read())
    head, old = parts[0], parts[1:]
    titles = [p.splitlines()[0] for p in old]
    for sec in sections:
        title = sec.splitlines()[0] if sec else ""
        body = sec.rstrip() + "\n\n"
        if title in titles:
            k = titles.index(title)
            old[k] = with_kept(body, old[k]).rstrip() + "\n\n"
        else:
            old.append(body)
            titles.append(title)
    note = (f"- Rerun with --only {','.join(names)}: " + "; ".join(line.lstrip("- ") for line in run_lines))
    head = head.rstrip() + "\n" + note + "\n\n"
    return head + "".join(p if p.endswith("\n\n") else p.rstrip() + "\n\n" for p in old).rstrip() + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer repetitions (smoke run)")
    parser.add_argument("--only", default="", help="comma-separated benchmark names (default: all)")
    parser.add_argument("--results", default=os.path.join(ROOT, "results", "bench", "results.json"))
    parser.add_argument("--doc", default=os.path.join(ROOT, "docs", "benchmarks.md"))
    args = parser.parse_args(argv)

    sys.path.insert(0, os.path.join(ROOT, "src"))
    sys.path.insert(0, HERE)
    benches = discover()
    wanted = [b for b in args.only.split(",") if b] or list(benches)
    unknown = [b for b in wanted if b not in benches]
    if unknown:
        parser.error(f"unknown benchmark(s) {unknown}; available: {sorted(benches)}")

    results: Dict[str, float] = {}
    if os.path.exists(args.results) and args.only:
        with open(args.results, encoding="utf-8") as handle:
            results.update(json.load(handle))
    sections = []
    failed = []
    for name in wanted:
        sys.stderr.write(f"[bench] {name} ...\n")
        t0 = time.perf_counter()
        try:
            out = run_one(name, benches[name], args.quick)
        except Exception:  # a broken benchmark is reported, the others still run
            failed.append(name)
            sections.append(f"## {name}\n\nFAILED:\n\n```\n{traceback.format_exc()}```\n")
            sys.stderr.write(traceback.format_exc())
            continue
        dt = time.perf_counter() - t0
        results.update({k: (float(v) if isinstance(v, (int, float)) else v) for k, v in out["results"].items()})
        sections.append(out.get("markdown", f"## {name}\n").rstrip() + f"\n\n_(ran in {dt:.0f} s)_\n")
        sys.stderr.write(f"[bench] {name} done in {dt:.1f} s\n")

    os.makedirs(os.path.dirname(args.results), exist_ok=True)
    with open(args.results, "w", encoding="utf-8") as handle:
        json.dump(results, handle, indent=2, sort_keys=True)
    header = ["# Benchmarks", "",
              "Written by `make bench` (bench/run.py); the same figures are in `results/bench/results.json`.",
              "Each section states the target it is measured against.",
              "Notes written by hand inside a section sit between `<!-- kept -->` and `<!-- /kept -->`: "
              "a rerun keeps them.", ""]
    intro = len(header)
    header += machine_description()
    if args.quick:
        header.append("- Mode: --quick (fewer repetitions; not the reference figures)")
    if failed:
        header.append(f"- FAILED: {', '.join(failed)}")
    if os.path.exists(args.doc) and not args.only:   # a full run keeps the sections' hand-written notes
        # (with --only, merge_doc below does it)
        with open(args.doc, encoding="utf-8") as handle:
            previous = {p.splitlines()[0]: p for p in _split_sections(handle.read())[1:]}
        sections = [with_kept(sec, previous.get(sec.splitlines()[0], "")) if sec else sec for sec in sections]
    text = "\n".join(header) + "\n\n" + "\n".join(sections)
    if args.only and os.path.exists(args.doc):
        text = merge_doc(args.doc, sections, header[intro:], wanted)  # date, machine, mode lines
    os.makedirs(os.path.dirname(args.doc), exist_ok=True)
    with open(args.doc, "w", encoding="utf-8") as handle:
        handle.write(text)
    sys.stderr.write(f"[bench] wrote {args.doc} and {args.results}\n")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
