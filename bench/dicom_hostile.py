#!/usr/bin/env python3
"""Hostile and misbehaving DICOM peers for bench/load_fault.sh (issue 22).

    dicom_hostile.py PORT MODE [COUNT] [SECONDS]

MODE:
  nested       C-STORE of a data set nested 10,000 sequences deep (360 KB)
  command      a C-STORE command set with 10,000 nested sequences in it
  garbage      COUNT connections sending random bytes
  huge         COUNT requests whose PDU length claims 4 GiB
  slowloris    COUNT connections sending an association request at 1 byte/s
               for SECONDS (or until cut)
  halfopen     COUNT connections that send nothing for SECONDS
Prints one line: what was sent and what came back (per connection: 'cut'
when the server closed it, 'answered 0xNNNN' for a C-STORE status).
"""
import os
import socket
import struct
import sys
import threading
import time

CT_IMAGE = "1.2.840.10008.5.1.4.1.1.2"
EXPLICIT_LE = "1.2.840.10008.1.2.1"


def item(kind, value):
    return struct.pack(">BBH", kind, 0, len(value)) + value


def pdu(kind, body):
    return struct.pack(">BBI", kind, 0, len(body)) + body


def associate_rq(calling="STORESCU"):
    body = struct.pack(">HH", 1, 0) + b"INTERSLICE".ljust(16)
    body += calling.encode().ljust(16) + bytes(32) + item(0x10, b"1.2.840.10008.3.1.1.1")
    body += item(0x20, bytes([1, 0, 0, 0]) + item(0x30, CT_IMAGE.encode()) +
                 item(0x40, EXPLICIT_LE.encode()))
    body += item(0x50, item(0x51, struct.pack(">I", 16384)) + item(0x52, b"1.2.3.4"))
    return pdu(0x01, body)


def pdata(command, last, fragment):
    return pdu(0x04, struct.pack(">IBB", len(fragment) + 2, 1,
                                 (1 if command else 0) | (2 if last else 0)) + fragment)


def element(el, value):
    if len(value) % 2:
        value += b"\0"
    return struct.pack("<HHI", 0, el, len(value)) + value


def store_command(sop_instance):
    body = (element(0x0002, CT_IMAGE.encode()) + element(0x0100, struct.pack("<H", 1)) +
            element(0x0110, struct.pack("<H", 1)) + element(0x0700, struct.pack("<H", 0)) +
            element(0x0800, struct.pack("<H", 0)) + element(0x1000, sop_instance))
    return element(0x0000, struct.pack("<I", len(body))) + body


def explicit(group, el, vr, value):
    if len(value) % 2:
        value += b"\0"
    return struct.pack("<HH2sH", group, el, vr, len(value)) + value


def nested(depth):
    head = (explicit(0x0008, 0x0016, b"UI", CT_IMAGE.encode()) +
            explicit(0x0008, 0x0018, b"UI", b"1.2.826.0.1.3680043.2.1125.9") +
            explicit(0x0008, 0x0060, b"CS", b"CT") +
            explicit(0x0020, 0x000D, b"UI", b"1.2.826.0.1.3680043.2.1125.1") +
            explicit(0x0020, 0x000E, b"UI", b"1.2.826.0.1.3680043.2.1125.2"))
    down = (struct.pack("<HH2sHI", 0x0040, 0xA730, b"SQ", 0, 0xFFFFFFFF) +
            struct.pack("<HHI", 0xFFFE, 0xE000, 0xFFFFFFFF)) * depth
    up = struct.pack("<HHIHHI", 0xFFFE, 0xE00D, 0, 0xFFFE, 0xE0DD, 0) * depth
    return head + down + up


def read_pdu(s, timeout):
    s.settimeout(timeout)
    try:
        head = b""
        while len(head) < 6:
            chunk = s.recv(6 - len(head))
            if not chunk:
                return None
            head += chunk
        length = struct.unpack(">I", head[2:6])[0]
        body = b""
        while len(body) < length:
            chunk = s.recv(min(65536, length - len(body)))
            if not chunk:
                return None
            body += chunk
        return head[0], body
    except (socket.timeout, OSError):
        return None


def status_of(answer):
    if answer is None:
        return "cut"
    kind, body = answer
    if kind == 0x07:
        return "aborted"
    if kind != 0x04:
        return "pdu 0x%02x" % kind
    command = body[6:]
    at = 0
    while at + 8 <= len(command):
        group, el, length = struct.unpack("<HHI", command[at:at + 8])
        if group == 0 and el == 0x0900:
            return "answered 0x%04X" % struct.unpack("<H", command[at + 8:at + 10])
        at += 8 + length
    return "answered (no status)"


def connect(port):
    s = socket.create_connection(("127.0.0.1", port), timeout=30)
    s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    return s


def send_chunks(s, payload, command):
    out = b""
    for at in range(0, len(payload), 16000):
        out += pdata(command, at + 16000 >= len(payload), payload[at:at + 16000])
    try:
        s.sendall(out)
    except OSError:
        pass


def main():
    port, mode = int(sys.argv[1]), sys.argv[2]
    count = int(sys.argv[3]) if len(sys.argv) > 3 else 1
    seconds = float(sys.argv[4]) if len(sys.argv) > 4 else 10
    results = []
    if mode in ("nested", "command"):
        s = connect(port)
        s.sendall(associate_rq())
        answer = read_pdu(s, 30)
        if answer is None or answer[0] != 0x02:
            print("%s: association not accepted" % mode)
            return
        if mode == "nested":
            s.sendall(pdata(True, True, store_command(b"1.2.826.0.1.3680043.2.1125.9")))
            send_chunks(s, nested(10000), False)
        else:
            send_chunks(s, store_command(b"1.2.3") + nested(10000), True)
        results.append(status_of(read_pdu(s, 60)))
        s.close()
    elif mode in ("garbage", "huge"):
        for _ in range(count):
            s = connect(port)
            try:
                if mode == "garbage":
                    s.sendall(os.urandom(4096))
                else:
                    s.sendall(bytes([1, 0, 0xFF, 0xFF, 0xFF, 0xFF]) + os.urandom(1024))
            except OSError:
                pass
            results.append(status_of(read_pdu(s, 30)))
            s.close()
    elif mode in ("slowloris", "halfopen"):
        def one(i):
            try:
                s = connect(port)
            except OSError:
                results.append("refused at connect")
                return
            end = time.time() + seconds
            rq = associate_rq()
            sent = 0
            outcome = "still open at the end"
            while time.time() < end:
                if mode == "slowloris" and sent < len(rq):
                    try:
                        s.send(rq[sent:sent + 1])
                        sent += 1
                    except OSError:
                        outcome = "cut after %d byte(s)" % sent
                        break
                s.settimeout(1.0)
                try:
                    if s.recv(1, socket.MSG_PEEK) == b"":
                        outcome = "cut after %d byte(s)" % sent
                        break
                except socket.timeout:
                    pass
                except OSError:
                    outcome = "cut after %d byte(s)" % sent
                    break
            results.append(outcome.split(" after")[0])
            s.close()
        threads = [threading.Thread(target=one, args=(i,)) for i in range(count)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    else:
        sys.exit("unknown mode " + mode)
    summary = {}
    for r in results:
        summary[r] = summary.get(r, 0) + 1
    print("%s x%d: %s" % (mode, len(results),
                          ", ".join("%s %d" % kv for kv in sorted(summary.items()))))


if __name__ == "__main__":
    main()
