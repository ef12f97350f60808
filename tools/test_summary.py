#!/usr/bin/env python3
"""One closing line for a test run made of several pytest runs: reads their JUnit XML files and
prints ``N passed, N failed, N skipped`` (errors count as failed); exit status 1 if any failed or if
no test ran at all.

    tools/test_summary.py runs/junit-parallel.xml runs/junit-serial.xml
"""
from __future__ import annotations

import sys
import xml.etree.ElementTree as ET


def counts(paths: list[str]) -> tuple[int, int, int]:
    passed = failed = skipped = 0
    for path in paths:
        try:
            root = ET.parse(path).getroot()
        except (OSError, ET.ParseError) as e:  # that run died before writing its report
            print(f"{path}: no test report ({e})", file=sys.stderr)
            failed += 1
            continue
        suites = [root] if root.tag == "testsuite" else root.findall("testsuite")
        for s in suites:
            tests, fail = int(s.get("tests", 0)), int(s.get("failures", 0)) + int(s.get("errors", 0))
            skip = int(s.get("skipped", 0))
            passed += tests - fail - skip
            failed += fail
            skipped += skip
    return passed, failed, skipped


def main(argv: list[str]) -> int:
    passed, failed, skipped = counts(argv)
    print(f"{passed} passed, {failed} failed, {skipped} skipped")
    return 1 if failed or passed == 0 else 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
