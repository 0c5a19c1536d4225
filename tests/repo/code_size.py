#!/usr/bin/env python3
"""Files and functions that grew too long to read as one thing.

    python3 tests/repo/code_size.py [--max-file-lines N] [--max-function-lines N]
                                    [--allow FILE] [ROOT] [FOLDER ...]

Counts the lines of every .h/.cc under the folders (default: server/) and
of every function body in them (a top-level or class-level definition: a
line that opens a brace after a parameter list, to its matching brace;
lambdas inside a function count as part of it). Prints the ones above the
limits (default 800 lines a file, 150 a function), one a line, and exits 1
when there is any that the allow file (lines "path" or "path:function",
each with a reason after " # ") does not list; an entry that no longer
matches is reported too, so the list only shrinks.
"""
import argparse
import os
import re
import sys

SIGNATURE_END = re.compile(r"\)\s*(const\s*)?(override\s*)?(noexcept\s*)?"
                           r"(->\s*[\w:<>,\s*&]+)?\s*\{\s*$")
NAME = re.compile(r"([A-Za-z_~][\w:~]*(?:operator\S*)?)\s*\(")
CONTROL = {"if", "for", "while", "switch", "catch", "return", "else", "do"}


def strip(line):
    """The line without string literals and // comments."""
    line = re.sub(r'"(\\.|[^"\\])*"', '""', line)
    line = re.sub(r"'(\\.|[^'\\])*'", "''", line)
    return line.split("//", 1)[0]


def functions(lines):
    """(name, first line, line count) of each function definition."""
    out = []
    depth = 0
    i = 0
    n = len(lines)
    in_block_comment = False
    while i < n:
        raw = lines[i]
        code = strip(raw)
        if in_block_comment:
            if "*/" in code:
                in_block_comment = False
            i += 1
            continue
        if "/*" in code and "*/" not in code:
            in_block_comment = True
        # A definition starts at namespace or class depth: its signature may
        # span lines; the line ending in "{" closes the parameter list.
        if SIGNATURE_END.search(code):
            # Find the signature's start (the line with the name and "(").
            # Back to the line that opens the parameter list: where the
            # parentheses read so far balance.
            j = i
            text = code
            while j > 0 and text.count("(") < text.count(")"):
                j -= 1
                text = strip(lines[j]) + text
            head = strip(lines[j])
            m = None
            for m in NAME.finditer(head):
                pass
            name = m.group(1) if m else "?"
            base = name.split("::")[-1]
            if base not in CONTROL and not head.lstrip().startswith(
                    ("namespace", "class", "struct", "enum", "#")):
                # Match braces from here.
                level = 0
                k = i
                while k < n:
                    c = strip(lines[k])
                    level += c.count("{") - c.count("}")
                    if level <= 0:
                        break
                    k += 1
                out.append((name, j + 1, k - j + 1))
                i = k + 1
                continue
        depth += code.count("{") - code.count("}")
        depth = max(depth, 0)
        i += 1
    return out


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--max-file-lines", type=int, default=800)
    parser.add_argument("--max-function-lines", type=int, default=150)
    parser.add_argument("--allow", default="")
    parser.add_argument("root", nargs="?", default=".")
    parser.add_argument("folders", nargs="*", default=["server"])
    args = parser.parse_args()
    allowed = {}
    if args.allow:
        with open(args.allow) as f:
            for line in f:
                line = line.strip()
                if not line or line.startswith("#"):
                    continue
                key, _, why = line.partition(" # ")
                allowed[key.strip()] = why.strip()
    found = []
    for folder in args.folders:
        for top, _, files in os.walk(os.path.join(args.root, folder)):
            for name in sorted(files):
                if not name.endswith((".h", ".cc")):
                    continue
                path = os.path.relpath(os.path.join(top, name), args.root)
                with open(os.path.join(args.root, path), encoding="utf-8",
                          errors="replace") as f:
                    lines = f.read().split("\n")
                if len(lines) > args.max_file_lines:
                    found.append((path, f"{path}: {len(lines)} lines"))
                for fn, start, length in functions(lines):
                    if length > args.max_function_lines:
                        found.append((f"{path}:{fn}",
                                      f"{path}:{start}: {fn}: {length} lines"))
    failed = False
    for key, text in found:
        if key in allowed:
            print(f"{text} (allowed: {allowed[key]})")
        else:
            print(text)
            failed = True
    for key in allowed:
        if key not in {k for k, _ in found}:
            print(f"{key}: allowed but no longer too long: remove it from "
                  f"{args.allow}")
            failed = True
    print(f"code size: {len(found)} above {args.max_file_lines} lines a file or "
          f"{args.max_function_lines} a function"
          f"{', all allowed' if found and not failed else ''}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
