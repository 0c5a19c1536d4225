#!/usr/bin/env python3
"""The DICOM port of the shipped Kubernetes Services is pinned by sender.

    python3 tests/repo/k8s_dicom_affinity.py ROOT    check ROOT/deploy/k8s/*.yaml
    python3 tests/repo/k8s_dicom_affinity.py --selftest

Why (docs/dicom-node.md, "Replicas"): each replica decides a series'
completeness from what it received itself. The shipped manifests once served
the DICOM port through a headless Service, so that a PACS sending one series
over several associations reached several pods, and each pod could turn its
part into a result. Every Service document that exposes port 11112 must
therefore have a cluster IP (not `clusterIP: None`) and
`sessionAffinity: ClientIP`. Text only (no YAML library on a bare machine).

Prints FILE: SERVICE: PROBLEM for each offence; exit 1 if any, else 0.
"""
import pathlib
import re
import sys

DICOM_PORT = re.compile(r'\bport:\s*11112\b')


def offences(text):
    """(service name, problem) for each Service that serves DICOM unpinned."""
    found = []
    for document in re.split(r'^---\s*$', text, flags=re.M):
        if not re.search(r'^kind:\s*Service\s*$', document, flags=re.M):
            continue
        if not DICOM_PORT.search(document):
            continue
        name = re.search(r'^\s+name:\s*(\S+)', document, flags=re.M)
        name = name.group(1) if name else '?'
        if re.search(r'^\s+clusterIP:\s*None\b', document, flags=re.M):
            found.append((name, 'headless: DNS gives each association any pod'))
        if not re.search(r'^\s+sessionAffinity:\s*ClientIP\b', document,
                         flags=re.M):
            found.append((name, 'no sessionAffinity: ClientIP'))
    return found


def selftest():
    old = ('apiVersion: v1\nkind: Service\nmetadata:\n  name: interslice\n'
           'spec:\n  clusterIP: None\n  ports:\n'
           '    - {name: dicom, port: 11112, targetPort: dicom}\n')
    new = ('apiVersion: v1\nkind: Service\nmetadata:\n  name: interslice-dicom\n'
           'spec:\n  sessionAffinity: ClientIP\n  ports:\n'
           '    - {name: dicom, port: 11112, targetPort: dicom}\n---\n'
           'kind: Service\nmetadata:\n  name: grpc\nspec:\n  clusterIP: None\n'
           '  ports:\n    - {name: grpc, port: 50051}\n')
    if len(offences(old)) != 2:
        print('selftest: the headless, unpinned DICOM Service was not refused')
        return 1
    if offences(new):
        print('selftest: a pinned DICOM Service beside a headless gRPC one was refused')
        return 1
    print('selftest: passed')
    return 0


def main(argv):
    if argv[1:] == ['--selftest']:
        return selftest()
    root = pathlib.Path(argv[1] if len(argv) > 1 else '.')
    files = sorted((root / 'deploy' / 'k8s').glob('*.yaml'))
    serving = 0
    status = 0
    for path in files:
        text = path.read_text()
        serving += len(DICOM_PORT.findall(text))
        for name, problem in offences(text):
            print(f'{path.relative_to(root)}: {name}: {problem}')
            status = 1
    if serving == 0:
        print(f'no manifest under {root}/deploy/k8s exposes port 11112')
        return 1
    return status


if __name__ == '__main__':
    sys.exit(main(sys.argv))
