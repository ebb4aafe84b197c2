"""Write tests/file_seconds.json, each test file's seconds in a `make test` run, from the JUnit
XML reports pytest writes there (`make test-run` writes test-output/junit-parallel.xml and
test-output/junit-serial.xml).

The parallel part of `make test` hands the files to its four workers heaviest first
(`order_heaviest_first` in tests/_scheduling.py): pytest-xdist's own order (the files with the
most tests first) left the few-test, long files (schemathesis, the fifty-student class, the
sorting example) to the end, and one worker ran on 50 s after the others had finished. The
figures only order the files; a file missing from them (a new one) goes after the measured ones.

Usage: python tools/test_seconds.py [REPORT.xml ...]   (from the repository root; default: the
two reports in test-output/)
"""

from __future__ import annotations

import argparse
import json
import sys
import xml.etree.ElementTree as ET
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "tests" / "file_seconds.json"
DEFAULT = [ROOT / "test-output" / "junit-parallel.xml", ROOT / "test-output" / "junit-serial.xml"]


def file_seconds(reports: list[Path]) -> dict[str, float]:
    """Seconds per test file (setup, call and teardown of its tests), summed over `reports`."""
    seconds: Counter[str] = Counter()
    for report in reports:
        for case in ET.parse(report).iter("testcase"):
            module = (case.get("classname") or "").split(".")
            name = next((part for part in module if part.startswith("test_")), None)
            if name is not None:
                seconds[f"{name}.py"] += float(case.get("time") or 0.0)
    return {name: round(s, 1) for name, s in sorted(seconds.items())}


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("reports", nargs="*", type=Path, help="JUnit XML reports (default: the "
                    "two in test-output/)")
    ap.add_argument("--out", type=Path, default=OUT, help=f"where to write (default: {OUT})")
    args = ap.parse_args(argv)
    reports = args.reports or [p for p in DEFAULT if p.exists()]
    if not reports:
        print("no JUnit reports: run `make test-run` first, or name them", file=sys.stderr)
        return 2
    missing = [str(p) for p in reports if not p.is_file()]
    if missing:
        print(f"no such report: {', '.join(missing)}", file=sys.stderr)
        return 2
    seconds = file_seconds(reports)
    args.out.write_text(json.dumps(seconds, indent=0, sort_keys=True) + "\n")
    print(f"{args.out}: {len(seconds)} files, {sum(seconds.values()):.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
