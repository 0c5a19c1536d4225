#!/usr/bin/env python3
"""Seeds for tests/fuzz/dicom_listener_fuzzer (see its header for the input
format): whole peer sessions (association request, C-ECHO, C-STORE of a small
CT slice, release) and bare data sets in each transfer syntax, made from
tests/data with DCMTK's command-line tools (dcmscale, dcmconv).

    python3 tests/fuzz/dicom_listener_seeds.py SEED_DIR
"""
import pathlib
import struct
import subprocess
import sys
import tempfile

CT_IMAGE = "1.2.840.10008.5.1.4.1.1.2"
VERIFICATION = "1.2.840.10008.1.1"
EXPLICIT_LE = "1.2.840.10008.1.2.1"
IMPLICIT_LE = "1.2.840.10008.1.2"


def item(kind, value):
    return struct.pack(">BBH", kind, 0, len(value)) + value


def pdu(kind, body):
    return struct.pack(">BBI", kind, 0, len(body)) + body


def associate_rq(called, calling):
    body = struct.pack(">HH", 1, 0)
    body += called.ljust(16).encode() + calling.ljust(16).encode() + bytes(32)
    body += item(0x10, b"1.2.840.10008.3.1.1.1")
    for cid, abstract, syntax in ((1, CT_IMAGE, EXPLICIT_LE),
                                  (3, VERIFICATION, IMPLICIT_LE)):
        body += item(0x20, bytes([cid, 0, 0, 0]) + item(0x30, abstract.encode()) +
                     item(0x40, syntax.encode()))
    body += item(0x50, item(0x51, struct.pack(">I", 16384)) +
                 item(0x52, b"1.2.3.4.5.6.7.8"))
    return pdu(0x01, body)


def pdata(context, command, last, fragment):
    control = (1 if command else 0) | (2 if last else 0)
    return pdu(0x04, struct.pack(">IBB", len(fragment) + 2, context, control) +
               fragment)


def element(tag_element, value):
    if len(value) % 2:
        value += b"\0"
    return struct.pack("<HHI", 0, tag_element, len(value)) + value


def command(*elements):
    body = b"".join(elements)
    return element(0x0000, struct.pack("<I", len(body))) + body


def us(tag_element, value):
    return element(tag_element, struct.pack("<H", value))


def session(dataset, sop_instance):
    out = associate_rq("INTERSLICE", "STORESCU")
    out += pdata(3, True, True, command(element(0x0002, VERIFICATION.encode()),
                                        us(0x0100, 0x0030), us(0x0110, 1),
                                        us(0x0800, 0x0101)))
    out += pdata(1, True, True, command(element(0x0002, CT_IMAGE.encode()),
                                        us(0x0100, 0x0001), us(0x0110, 2),
                                        us(0x0700, 0), us(0x0800, 0),
                                        element(0x1000, sop_instance)))
    for at in range(0, len(dataset), 8000):
        out += pdata(1, False, at + 8000 >= len(dataset),
                     dataset[at:at + 8000])
    return out + pdu(0x05, bytes(4))


def sop_instance_of(path):
    text = subprocess.run(["dcmdump", "+P", "0008,0018", "-s", str(path)],
                          check=True, capture_output=True, text=True).stdout
    return text.split("[", 1)[1].split("]", 1)[0].encode()


def main():
    seeds = pathlib.Path(sys.argv[1])
    seeds.mkdir(parents=True, exist_ok=True)
    root = pathlib.Path(__file__).resolve().parents[2]
    slices = sorted((root / "tests/data/ct-thick").glob("*.dcm"))[:2]
    with tempfile.TemporaryDirectory() as tmp:
        for n, path in enumerate(slices):
            small = pathlib.Path(tmp) / f"small{n}.dcm"
            subprocess.run(["dcmscale", "--quiet", "--scale-x-size", "32",
                            str(path), str(small)], check=True)
            for syntax, flag in ((0, "+ti"), (1, "+te"), (2, "+tb"),
                                 (3, "+td")):
                raw = pathlib.Path(tmp) / f"raw{n}-{syntax}"
                subprocess.run(["dcmconv", "--quiet", "-F", flag, str(small),
                                str(raw)], check=True)
                (seeds / f"dataset-{n}-{syntax}").write_bytes(
                    bytes([1, syntax]) + raw.read_bytes())
            raw = pathlib.Path(tmp) / f"raw{n}-1"
            (seeds / f"session-{n}").write_bytes(
                bytes([0]) + session(raw.read_bytes(), sop_instance_of(small)))
    # Nesting just past the scan's limit, in a data set and in a command.
    nested = b"".join(struct.pack("<HH2sHI", 0x0040, 0xA730, b"SQ", 0,
                                  0xFFFFFFFF) + struct.pack("<HHI", 0xFFFE,
                                                            0xE000, 0xFFFFFFFF)
                      for _ in range(40))
    nested += struct.pack("<HHIHHI", 0xFFFE, 0xE00D, 0, 0xFFFE, 0xE0DD, 0) * 40
    (seeds / "dataset-nested").write_bytes(bytes([1, 1]) + nested)
    (seeds / "session-nested-command").write_bytes(
        bytes([0]) + associate_rq("INTERSLICE", "X") +
        pdata(1, True, True, command(us(0x0100, 1)) + nested))


if __name__ == "__main__":
    main()
