#!/usr/bin/env python3
"""STOW-RS intake (server/net/dicomweb/stow.h): a 300-instance series in one
STOW-RS request to interslice-server on loopback, and the time from the
request's start to its job's start with complete_on_request (issue 27's goal:
<= 3 s). The series is ../shared/data/ct-head-phantom-thin (140 slices of
about 515 KiB) taken 300 times, each copy a new SOP instance (dcmodify), so
one series of 300 instances (about 150 MB); skipped (exit 0) without that
folder. Every instance is fsynced before the answer, so the disk sets the
pace. Medians of REPEAT runs (default 3), each on a fresh server.

  python3 bench/stow_receive.py [build-dir]     (N=300 REPEAT=3)
"""
import datetime
import glob
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time

root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
build = sys.argv[1] if len(sys.argv) > 1 else os.path.join(root, "build")
server = os.path.join(build, "server", "interslice-server")
source = os.path.join(root, "..", "shared", "data", "ct-head-phantom-thin")
n = int(os.environ.get("N", "300"))
repeat = int(os.environ.get("REPEAT", "3"))
if not os.path.isdir(source):
    print("stow_receive: skipped: no ct-head-phantom-thin in ../shared/data")
    sys.exit(0)

work = tempfile.mkdtemp(prefix="interslice-stow-bench.")
try:
    files = sorted(glob.glob(os.path.join(source, "*.dcm")))
    os.makedirs(os.path.join(work, "series"))
    body_path = os.path.join(work, "body")
    boundary = b"interslice-stow-bench"
    with open(body_path, "wb") as body:
        for i in range(n):
            copy = os.path.join(work, "series", "%04d.dcm" % i)
            shutil.copyfile(files[i % len(files)], copy)
            subprocess.run(["dcmodify", "-nb", "-q", "-m",
                            "(0008,0018)=2.25.%d%04d" % (os.getpid(), i),
                            copy], check=True)
            body.write(b"--" + boundary +
                       b"\r\nContent-Type: application/dicom\r\n\r\n")
            with open(copy, "rb") as f:
                body.write(f.read())
            body.write(b"\r\n")
        body.write(b"--" + boundary + b"--\r\n")
    size = os.path.getsize(body_path)
    with open(os.path.join(work, "rules.yaml"), "w") as f:
        f.write("stable_seconds: 600\nrules: [{name: ct, match: {modality: CT},"
                " complete_on_request: true, job: {threshold: 300, roi: [0, 0,"
                " 0, 64, 64, 4]}}]\n")

    def stamp(line):
        t = line.split(" ", 1)[0]
        return datetime.datetime.fromisoformat(t).timestamp()

    uploads, to_start = [], []
    for run in range(repeat):
        spool = os.path.join(work, "spool%d" % run)
        ports = os.path.join(work, "ports%d" % run)
        log_path = os.path.join(work, "log%d" % run)
        log = open(log_path, "w")
        proc = subprocess.Popen(
            [server, "--listen", "127.0.0.1:0", "--spool", spool,
             "--port-file", ports, "--dicom-listen", "127.0.0.1:0",
             "--rules", os.path.join(work, "rules.yaml"), "--http-listen",
             "127.0.0.1:0", "--isolation", "thread"],
            stdout=log, stderr=subprocess.STDOUT)
        try:
            for _ in range(400):
                if os.path.exists(ports) and len(open(ports).read().split()) >= 4:
                    break
                time.sleep(0.05)
            http_port = open(ports).read().split()[3]
            t0 = time.time()
            r = subprocess.run(
                ["curl", "-s", "-S", "-o", os.devnull, "-w", "%{http_code}",
                 "-H", "Content-Type: multipart/related; "
                 "type=\"application/dicom\"; boundary=" + boundary.decode(),
                 "--data-binary", "@" + body_path,
                 "http://127.0.0.1:%s/dicomweb/studies" % http_port],
                capture_output=True, text=True)
            t1 = time.time()
            if r.stdout != "200":
                sys.exit("stow_receive: HTTP %s %s\n%s" %
                         (r.stdout, r.stderr, open(log_path).read()))
            started = None
            for _ in range(600):
                m = [l for l in open(log_path) if re.search(r"job=\S+ started", l)]
                if m:
                    started = stamp(m[0])
                    break
                time.sleep(0.05)
            if started is None:
                sys.exit("stow_receive: no job started\n" + open(log_path).read())
            uploads.append(t1 - t0)
            to_start.append(started - t0)
        finally:
            proc.terminate()
            proc.wait()
            log.close()
    cpus = os.cpu_count()
    load = open("/proc/loadavg").read().split()[0]
    print("stow_receive: %d instances, %.1f MB in one request; %d CPU(s), "
          "load %s" % (n, size / 1e6, cpus, load))
    print("  request (upload, fsync of every instance, answer): median %.2f s, "
          "%.0f instances/s (runs: %s)" %
          (statistics.median(uploads), n / statistics.median(uploads),
           " ".join("%.2f" % u for u in uploads)))
    print("  request start -> job started (complete_on_request): median %.2f s "
          "(runs: %s); goal <= 3 s" %
          (statistics.median(to_start), " ".join("%.2f" % s for s in to_start)))
finally:
    shutil.rmtree(work, ignore_errors=True)
