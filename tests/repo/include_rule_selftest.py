#!/usr/bin/env python3
"""The include rule's checker can fail: a tree with one planted violation of
each rule (and the allowed includes next to them) must give exactly those
violations, and the same tree without them none.

    python3 tests/repo/include_rule_selftest.py
"""
import os
import subprocess
import sys
import tempfile

HERE = os.path.dirname(os.path.abspath(__file__))
CHECKER = os.path.join(HERE, "include_rule.py")

# (file, include, the rule it breaks or None when it is allowed)
CASES = [
    ("core/sdf/a.cc", "job/job.h", "core-is-pure"),
    ("core/sdf/a.cc", "interslice/v1/interslice.pb.h", "core-is-pure"),
    ("core/sdf/a.cc", "core/common/compute.h", None),
    ("job/a.cc", "server/engine/spool.h", "job-below-server"),
    ("job/a.cc", "core/pipeline/pipeline.h", None),
    ("server/base/a.cc", "server/engine/spool.h", "base-is-the-bottom"),
    ("server/engine/a.cc", "server/node/peer.h", "engine-below-node"),
    ("server/engine/a.cc", "server/base/log_safe.h", None),
    ("server/node/a.cc", "server/net/dimse/scu.h", "node-below-net"),
    ("server/node/a.cc", "server/engine/job_manager.h", None),
    ("server/node/a.cc", "dcmtk/dcmdata/dcfilefo.h", None),
    ("server/node/a.cc", "dcmtk/dcmnet/diutil.h", "dimse-only-in-net-dimse"),
    ("server/net/dimse/a.cc", "server/net/dicomweb/http.h", "doors-apart"),
    ("server/net/dicomweb/a.cc", "server/net/dimse/scu.h", "doors-apart"),
    ("server/net/dimse/a.cc", "dcmtk/dcmnet/scu.h", None),
    ("server/net/dimse/a.cc", "server/app/server.h", "net-below-app"),
    ("server/net/dicomweb/a.cc", "curl/curl.h", None),
    ("server/net/http/a.cc", "server/net/dicomweb/stow.h",
     "http-knows-no-door"),
    ("server/net/dicomweb/a.cc", "server/net/http/http_handler.h", None),
    ("server/net/grpc/a.cc", "curl/curl.h", "curl-only-in-dicomweb"),
    ("server/net/http/a.cc", "civetweb.h", None),
    ("server/net/grpc/a.cc", "civetweb.h", "http-server-only-in-net-http"),
    ("server/net/grpc/a.cc", "grpcpp/grpcpp.h", None),
    ("server/app/a.cc", "grpcpp/grpcpp.h", None),
    ("server/node/a.cc", "grpcpp/grpcpp.h", "grpc-at-the-edge"),
    ("server/engine/a.cc", "interslice/v1/interslice.grpc.pb.h",
     "grpc-at-the-edge"),
    ("server/node/a.cc", "client/remote_commands.h", "client-not-in-server"),
]


def run(root):
    done = subprocess.run([sys.executable, CHECKER, root], capture_output=True,
                          text=True)
    lines = [l for l in done.stdout.splitlines() if "rule " in l and ": #include" in l]
    return done.returncode, lines


def main():
    failures = []
    with tempfile.TemporaryDirectory() as root:
        for path, include, _ in CASES:
            full = os.path.join(root, path)
            os.makedirs(os.path.dirname(full), exist_ok=True)
            with open(full, "a") as f:
                f.write(f'#include "{include}"\n')
        code, lines = run(root)
        expected = sorted(f'{p}: "{i}" {r}' for p, i, r in CASES if r)
        got = []
        for line in lines:
            path = line.split(":", 1)[0]
            include = line.split('#include "', 1)[1].split('"', 1)[0]
            rule = line.split(": rule ", 1)[1].split(":", 1)[0]
            got.append(f'{path}: "{include}" {rule}')
        got.sort()
        if code != 1:
            failures.append(f"planted violations: exit {code}, expected 1")
        for e in expected:
            if e not in got:
                failures.append(f"not found: {e}")
        for g in got:
            if g not in expected:
                failures.append(f"reported but allowed: {g}")
    with tempfile.TemporaryDirectory() as root:
        for path, include, rule in CASES:
            if rule:
                continue
            full = os.path.join(root, path)
            os.makedirs(os.path.dirname(full), exist_ok=True)
            with open(full, "a") as f:
                f.write(f'#include "{include}"\n')
        code, lines = run(root)
        if code != 0 or lines:
            failures.append(f"allowed includes only: exit {code}, {lines}")
    for f in failures:
        print("include rule selftest:", f)
    if failures:
        return 1
    print(f"include rule selftest: {sum(1 for c in CASES if c[2])} planted "
          f"violations found, {sum(1 for c in CASES if not c[2])} allowed "
          "includes passed")
    return 0


if __name__ == "__main__":
    sys.exit(main())
