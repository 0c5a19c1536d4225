#!/usr/bin/env python3
"""No build argument in a Dockerfile's WORKDIR, COPY or ADD.

    python3 tests/repo/dockerfile_args.py ROOT     check ROOT/deploy/**/Dockerfile*
    python3 tests/repo/dockerfile_args.py --selftest

Why: buildah 1.28 (Debian bookworm's podman) keys a cached WORKDIR layer
without the value of the argument it names. A build with
`--build-arg SOURCE_DIR=/a` after one with `/b` reused the WORKDIR layer of
`/b`, copied into it and then ran the next RUN in `/a`, where nothing was:
"bash: scripts/install-deps.sh: No such file or directory" (a CI run in a
checkout at a new path failed so). An argument may still be used inside RUN,
whose cache key holds it.

Prints FILE:LINE: INSTRUCTION for each offence; exit 1 if any, else 0.
"""
import pathlib
import re
import sys

ARG_RE = re.compile(r'^\s*ARG\s+([A-Za-z_][A-Za-z0-9_]*)', re.IGNORECASE)
INSTRUCTION_RE = re.compile(r'^\s*(WORKDIR|COPY|ADD)\s+(.*)$', re.IGNORECASE)


def offences(text):
    """(line number, line) of each WORKDIR/COPY/ADD naming a declared ARG."""
    declared = set()
    found = []
    for number, line in enumerate(text.splitlines(), start=1):
        match = ARG_RE.match(line)
        if match:
            declared.add(match.group(1))
            continue
        match = INSTRUCTION_RE.match(line)
        if not match:
            continue
        for name in declared:
            if re.search(r'\$\{?' + re.escape(name) + r'\b', match.group(2)):
                found.append((number, line.strip()))
                break
    return found


def selftest():
    bad = 'FROM x\nARG SOURCE_DIR=/src\nWORKDIR ${SOURCE_DIR}\nCOPY a $SOURCE_DIR/a\n'
    good = ('FROM x\nCOPY a /fixed/a\nARG SOURCE_DIR=/src\n'
            'RUN mkdir -p "$SOURCE_DIR" && cd "$SOURCE_DIR"\n'
            'WORKDIR /fixed\nCOPY --from=build /out/bin/ /usr/local/bin/\n')
    if [n for n, _ in offences(bad)] != [3, 4]:
        print('selftest: the planted WORKDIR and COPY were not both found')
        return 1
    if offences(good):
        print('selftest: a Dockerfile using its argument only in RUN was refused')
        return 1
    print('selftest: passed')
    return 0


def main(argv):
    if argv[1:] == ['--selftest']:
        return selftest()
    root = pathlib.Path(argv[1] if len(argv) > 1 else '.')
    files = sorted(root.glob('deploy/**/Dockerfile*'))
    if not files:
        print(f'no Dockerfile under {root}/deploy')
        return 1
    status = 0
    for path in files:
        for number, line in offences(path.read_text()):
            print(f'{path.relative_to(root)}:{number}: {line}')
            status = 1
    return status


if __name__ == '__main__':
    sys.exit(main(sys.argv))
