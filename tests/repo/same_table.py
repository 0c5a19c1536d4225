#!/usr/bin/env python3
"""The completeness table is stated once: docs/dicom-node.md and
docs/dicomweb.md hold the same block between the markers
<!-- completeness-table ... --> and <!-- /completeness-table -->, so that the
two doors' documents cannot drift apart (issue 39).

    python3 tests/repo/same_table.py [ROOT]
"""
import re
import sys
from pathlib import Path

DOCS = ["docs/dicom-node.md", "docs/dicomweb.md"]
BLOCK = re.compile(r"<!-- completeness-table.*?-->\n(.*?)<!-- /completeness-table -->",
                   re.S)


def main():
    root = Path(sys.argv[1] if len(sys.argv) > 1 else ".")
    tables = {}
    for doc in DOCS:
        found = BLOCK.findall((root / doc).read_text(encoding="utf-8"))
        if len(found) != 1:
            print(f"{doc}: expected one completeness table, found {len(found)}")
            return 1
        if found[0].count("\n|") < 5:
            print(f"{doc}: the completeness table has fewer than 5 rows")
            return 1
        tables[doc] = found[0]
    first, second = (tables[d] for d in DOCS)
    if first != second:
        for a, b in zip(first.splitlines(), second.splitlines()):
            if a != b:
                print(f"the completeness tables differ:\n  {DOCS[0]}: {a}\n  {DOCS[1]}: {b}")
                break
        else:
            print("the completeness tables differ in length")
        return 1
    print(f"completeness table: the same {first.count(chr(10))} lines in both")
    return 0


if __name__ == "__main__":
    sys.exit(main())
