#!/usr/bin/env python3
"""The N slowest tests of this run, from ctest's JUnit files (--output-junit).

    scripts/slowest-tests.py N STAGE=FILE.xml [STAGE=FILE.xml ...]

Prints a table (seconds, stage, status, test name), slowest first. Files
that do not exist (a stage that did not run) are skipped.
"""
import os
import sys
import xml.etree.ElementTree as ElementTree


def main():
    count = int(sys.argv[1])
    rows = []
    for spec in sys.argv[2:]:
        stage, _, path = spec.partition("=")
        if not os.path.exists(path):
            continue
        for case in ElementTree.parse(path).getroot().iter("testcase"):
            status = case.get("status", "run")
            if case.find("failure") is not None:
                status = "failed"
            elif case.find("skipped") is not None:
                status = "skipped"
            rows.append((float(case.get("time", "0")), stage, status,
                         case.get("name", "?")))
    rows.sort(reverse=True)
    if not rows:
        print("  (no test results)")
        return
    print(f"  {'seconds':>8}  {'stage':<16} {'status':<8} test")
    for seconds, stage, status, name in rows[:count]:
        print(f"  {seconds:8.1f}  {stage:<16} {status:<8} {name}")


if __name__ == "__main__":
    main()
