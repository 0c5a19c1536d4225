#!/usr/bin/env python3
"""The include rule: which folder of the project may include which.

    python3 tests/repo/include_rule.py [ROOT]

Reads every #include of every .h/.cc under core/, job/, client/, server/ and
holds it against RULES below. Prints one line per violation,
"path:line: #include "x": rule NAME: why", and exits 1 when there is any;
exits 0 and says how many includes it read otherwise. The layers are the
ones docs/DESIGN.md ("The server's layers") and README.md's layout table
describe; a change to them is a change to this table.
"""
import os
import re
import sys

# A rule: (name, files it governs (path prefixes), forbidden include patterns
# (regular expressions matched against the included path), why).
RULES = [
    ("core-is-pure", ["core/"],
     [r"^(job|server|client)/", r"^interslice/", r"^grpc", r"^google/protobuf",
      r"\.pb\.h$"],
     "core/ knows nothing of the job layer, the server, the CLI, gRPC or "
     "protobuf"),
    ("job-below-server", ["job/"],
     [r"^(server|client)/", r"^grpc"],
     "the job layer knows the wire spec, never gRPC, the server or the CLI"),
    ("client-not-in-server", ["server/"],
     [r"^client/"],
     "the server includes nothing of the CLI"),
    ("base-is-the-bottom", ["server/base/"],
     [r"^server/(engine|node|net|app)/"],
     "server/base/ is below every other layer of the server"),
    ("engine-below-node", ["server/engine/"],
     [r"^server/(node|net|app)/"],
     "the engine runs jobs; the DICOM node and the protocols are above it"),
    ("node-below-net", ["server/node/"],
     [r"^server/(net|app)/"],
     "the node knows no protocol: every door calls it, it calls none"),
    ("net-below-app", ["server/net/"],
     [r"^server/app/"],
     "the protocols are wired together only in server/app/"),
    ("doors-apart", ["server/net/dimse/"],
     [r"^server/net/dicomweb/"],
     "net/dimse and net/dicomweb never include each other"),
    ("doors-apart", ["server/net/dicomweb/"],
     [r"^server/net/dimse/"],
     "net/dimse and net/dicomweb never include each other"),
    ("http-knows-no-door", ["server/net/http/"],
     [r"^server/net/dicomweb/"],
     "net/http is the listener: the DICOMweb door plugs into it through "
     "its route interface (server/net/http/http_handler.h), never the other "
     "way"),
    ("dimse-only-in-net-dimse", ["core/", "job/", "client/", "server/"],
     [r"^dcmtk/(dcmnet|dcmtls)/"],
     "DCMTK's network headers (dcmnet, dcmtls) only in server/net/dimse/"),
    ("curl-only-in-dicomweb", ["core/", "job/", "client/", "server/"],
     [r"^curl/"],
     "libcurl only in server/net/dicomweb/"),
    ("http-server-only-in-net-http", ["core/", "job/", "client/", "server/"],
     [r"^civetweb\.h$"],
     "the HTTP server library only in server/net/http/"),
    ("grpc-at-the-edge", ["server/"],
     [r"^grpc\+\+/", r"^grpcpp/", r"^grpc/", r"\.grpc\.pb\.h$"],
     "gRPC only in server/net/grpc/ and server/app/"),
]

# Where a pattern is allowed although a rule above matches (the folders
# each library belongs to).
EXEMPT = {
    "dimse-only-in-net-dimse": ["server/net/dimse/"],
    "curl-only-in-dicomweb": ["server/net/dicomweb/"],
    "http-server-only-in-net-http": ["server/net/http/"],
    "grpc-at-the-edge": ["server/net/grpc/", "server/app/"],
}

INCLUDE = re.compile(r'^\s*#\s*include\s*[<"]([^>"]+)[>"]')
GOVERNED = ("core/", "job/", "client/", "server/")


def violations(root):
    found = []
    count = 0
    for top in GOVERNED:
        for folder, _, files in os.walk(os.path.join(root, top)):
            for name in sorted(files):
                if not name.endswith((".h", ".cc")):
                    continue
                path = os.path.relpath(os.path.join(folder, name), root)
                with open(os.path.join(root, path), encoding="utf-8",
                          errors="replace") as f:
                    for line_no, line in enumerate(f, 1):
                        m = INCLUDE.match(line)
                        if not m:
                            continue
                        count += 1
                        included = m.group(1)
                        for rule, scope, patterns, why in RULES:
                            if not any(path.startswith(s) for s in scope):
                                continue
                            if any(path.startswith(e)
                                   for e in EXEMPT.get(rule, [])):
                                continue
                            if any(re.search(p, included) for p in patterns):
                                found.append(
                                    f'{path}:{line_no}: #include "{included}":'
                                    f" rule {rule}: {why}")
    return found, count


def main():
    root = sys.argv[1] if len(sys.argv) > 1 else os.path.join(
        os.path.dirname(os.path.abspath(__file__)), "..", "..")
    found, count = violations(os.path.abspath(root))
    for line in found:
        print(line)
    if found:
        print(f"include rule: {len(found)} violation(s)")
        return 1
    print(f"include rule: {count} includes read, none breaks a rule")
    return 0


if __name__ == "__main__":
    sys.exit(main())
