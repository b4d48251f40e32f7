#!/usr/bin/env python3
"""cvislam_link_impair against Python servers on 127.0.0.1: the latency it adds, its rate cap, a cut blackout that
resets the open connection and refuses new ones until it ends, and a freeze that holds data without closing.

  test/chaos/link_impair_test.py BIN_DIR        (CTest: chaos_link_impair)
"""
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time

BIN = os.path.join(sys.argv[1], "cvislam_link_impair")
failures = []


def check(ok, what):
    print(("ok    " if ok else "FAIL  ") + what, flush=True)
    if not ok:
        failures.append(what)


def serve(handler):
    """A listening socket on 127.0.0.1; handler(conn) per connection on a thread. Returns the port."""
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    s.listen(64)

    def accept():
        while True:
            conn, _ = s.accept()
            threading.Thread(target=handler, args=(conn,), daemon=True).start()

    threading.Thread(target=accept, daemon=True).start()
    return s.getsockname()[1]


def echo(conn):
    try:
        while True:
            data = conn.recv(65536)
            if not data:
                break
            conn.sendall(data)
    except OSError:
        pass
    conn.close()


def sink(conn):
    total = 0
    try:
        while True:
            data = conn.recv(65536)
            if not data:
                break
            total += len(data)
    except OSError:
        pass
    conn.sendall(str(total).encode())
    conn.close()


class Proxy:
    def __init__(self, target_port, *options):
        self.dir = tempfile.mkdtemp(prefix="link_impair_")
        port_file = os.path.join(self.dir, "port")
        self.proc = subprocess.Popen([BIN, "--listen", "127.0.0.1:0", "--target", f"127.0.0.1:{target_port}",
                                      "--port-file", port_file, *options], stdout=subprocess.PIPE, text=True)
        for _ in range(200):
            if os.path.exists(port_file) and open(port_file).read().strip():
                break
            time.sleep(0.01)
        self.port = int(open(port_file).read())
        self.t0 = time.monotonic()

    def connect(self):
        return socket.create_connection(("127.0.0.1", self.port), timeout=10)

    def stop(self):
        self.proc.terminate()
        out, _ = self.proc.communicate(timeout=10)
        return self.proc.returncode, out


def round_trips(proxy, n=20):
    times = []
    with proxy.connect() as c:
        for _ in range(n):
            start = time.monotonic()
            c.sendall(b"x" * 64)
            got = 0
            while got < 64:
                got += len(c.recv(64 - got))
            times.append(time.monotonic() - start)
    return times


def test_latency():
    proxy = Proxy(serve(echo), "--latency-ms", "50")
    rtt_ms = 1000 * statistics.median(round_trips(proxy))
    code, out = proxy.stop()
    check(95 <= rtt_ms <= 130, f"latency 50 ms each way: round trip {rtt_ms:.1f} ms (expected 100-130)")
    check(code == 0 and "up_bytes=" in out, f"summary at SIGTERM, exit 0 ({out.strip()})")


def test_rate():
    proxy = Proxy(serve(sink), "--up-kbit", "1000")
    payload = b"y" * 500_000
    start = time.monotonic()
    with proxy.connect() as c:
        c.sendall(payload)
        c.shutdown(socket.SHUT_WR)
        received = int(c.recv(64).decode())
    seconds = time.monotonic() - start
    proxy.stop()
    kbit_s = 8 * len(payload) / seconds / 1000
    check(received == len(payload), f"every byte arrives under the cap ({received})")
    check(900 <= kbit_s <= 1100, f"--up-kbit 1000: {kbit_s:.0f} kbit/s (expected 900-1100)")


def test_cut():
    proxy = Proxy(serve(echo), "--blackout", "1:1.5:cut")
    c = proxy.connect()
    c.settimeout(5)
    reset = False
    try:
        time.sleep(1.2)
        c.sendall(b"after the cut")
        reset = c.recv(64) == b""
    except OSError:
        reset = True
    check(reset, "a cut blackout resets the open connection")
    refused = False
    try:
        with proxy.connect() as d:
            d.settimeout(2)
            d.sendall(b"during")
            refused = d.recv(64) == b""
    except OSError:
        refused = True
    check(refused, "a connection during the cut is refused")
    time.sleep(max(0.0, 2.7 - (time.monotonic() - proxy.t0)))
    with proxy.connect() as e:
        e.sendall(b"back")
        check(e.recv(64) == b"back", "after the cut a new connection works")
    proxy.stop()


def test_freeze():
    proxy = Proxy(serve(echo), "--blackout", "1:1.5:freeze")
    with proxy.connect() as c:
        c.settimeout(10)
        time.sleep(1.1)
        start = time.monotonic()
        c.sendall(b"held")
        answer = c.recv(64)
        waited = time.monotonic() - start
    proxy.stop()
    check(answer == b"held", "a frozen connection stays open and delivers afterwards")
    check(1.2 <= waited <= 2.0, f"data waits until the freeze ends ({waited:.2f} s, expected 1.2-2.0)")


def test_bad_options():
    result = subprocess.run([BIN, "--listen", "127.0.0.1:0", "--target", "127.0.0.1:9", "--latency-ms", "abc"],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    check(result.returncode == 2 and "--latency-ms" in result.stdout, "a bad option is named, exit 2")


for test in (test_latency, test_rate, test_cut, test_freeze, test_bad_options):
    test()
sys.exit(1 if failures else 0)
