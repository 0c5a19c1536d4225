#!/usr/bin/env python3
"""A TCP proxy whose answers start late: every connection's first bytes from
the backend are held for DELAY seconds (a distant server, a TLS handshake over
a WAN, a loaded host), then everything is relayed as it comes.

  slow_proxy.py BACKEND_PORT DELAY_SECONDS PORT_FILE

Listens on 127.0.0.1 (an ephemeral port, written to PORT_FILE once
listening); runs until killed. Used by tests/server/app/server_test.cc (SlowHandshakeIsNotAConnectionFailure).
"""
import socket
import sys
import threading
import time


def pump(src, dst, delay):
    first = True
    try:
        while True:
            data = src.recv(65536)
            if not data:
                break
            if first and delay > 0:
                time.sleep(delay)
            first = False
            dst.sendall(data)
    except OSError:
        pass
    finally:
        for s in (src, dst):
            try:
                s.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass


def main():
    backend_port, delay, port_file = int(sys.argv[1]), float(sys.argv[2]), sys.argv[3]
    listener = socket.socket()
    listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    listener.bind(("127.0.0.1", 0))
    listener.listen(16)
    with open(port_file + ".tmp", "w") as f:
        f.write(str(listener.getsockname()[1]))
    import os
    os.rename(port_file + ".tmp", port_file)
    while True:
        client, _ = listener.accept()
        backend = socket.create_connection(("127.0.0.1", backend_port))
        threading.Thread(target=pump, args=(client, backend, 0), daemon=True).start()
        threading.Thread(target=pump, args=(backend, client, delay), daemon=True).start()


if __name__ == "__main__":
    main()
