#!/usr/bin/env python3
"""Cost of TLS + user/password + access control on the diffpos bus (prints a table).

Starts a Python zenoh router in a subprocess twice: plain ``tcp/`` on loopback (the
unauthenticated default) and the secured configuration rendered from a throw-away profile
(certificates generated into a temporary folder). For each it measures, between two client
sessions through the router:

- round trip: the emulator puts ``run/control``, the anchor answers with a range put, the
  emulator receives it (two router hops each way) [us, median and 99th percentile];
- throughput: one anchor puts N range messages (200 bytes, congestion control BLOCK) to a
  recorder subscriber [messages/s, wall time from first put to last receipt].

example:
  python security/bench_overhead.py --rounds 2000 --messages 50000
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import zenoh
from diffpos_services.bus.security.certs import make_dev_certs
from diffpos_services.bus.security.configs import client_config, to_zenoh
from diffpos_services.bus.security.credentials import write_credentials
from diffpos_services.bus.security.profile import load_profile
from diffpos_services.bus.security.render import render_profile
from diffpos_services.wire.keys import Keys

ROUTER = """
import sys, zenoh
with zenoh.open(zenoh.Config.from_file(sys.argv[1])) as s:
    print("READY", flush=True)
    sys.stdin.read()
"""


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _start(path: Path) -> subprocess.Popen:
    p = subprocess.Popen([sys.executable, "-c", ROUTER, str(path)], stdin=subprocess.PIPE,
                         stdout=subprocess.PIPE, text=True, start_new_session=True)
    if not p.stdout.readline().startswith("READY"):
        raise RuntimeError("router did not start")
    return p


def _stop(p: subprocess.Popen) -> None:
    p.stdin.close()
    try:
        p.wait(timeout=5)
    except subprocess.TimeoutExpired:
        os.killpg(p.pid, signal.SIGKILL)
        p.wait()


def _measure(cfg_emulator: dict, cfg_anchor: dict, rounds: int, messages: int) -> tuple[float, float, float]:
    k = Keys("bench")
    bc = zenoh.CongestionControl.BLOCK
    with zenoh.open(to_zenoh(cfg_emulator)) as emu, zenoh.open(to_zenoh(cfg_anchor)) as anc:
        back = threading.Event()
        count = [0]
        done = threading.Event()
        rng = anc.declare_publisher(k.anchor_range("uav1", "n01"), congestion_control=bc)
        anc.declare_subscriber(k.run_control(), lambda s: rng.put(b"x" * 200))

        def on_range(_s) -> None:
            count[0] += 1
            back.set()
            if count[0] == messages:
                done.set()

        emu.declare_subscriber(k.anchor_ranges(), on_range)
        ctl = emu.declare_publisher(k.run_control(), congestion_control=bc)
        for p in (ctl, rng):
            ok = threading.Event()
            lis = p.declare_matching_listener(lambda st, ok=ok: ok.set() if st.matching else None)
            if p.matching_status.matching:
                ok.set()
            if not ok.wait(10):
                raise RuntimeError("no match")
            lis.undeclare()
        rtt = np.empty(rounds)
        for i in range(rounds):
            back.clear()
            t0 = time.perf_counter_ns()
            ctl.put(b"go")
            if not back.wait(10):
                raise RuntimeError("round trip lost")
            rtt[i] = (time.perf_counter_ns() - t0) / 1e3
        count[0] = 0
        done.clear()
        payload = b"x" * 200
        t0 = time.perf_counter()
        for _ in range(messages):
            rng.put(payload)
        if not done.wait(120):
            raise RuntimeError(f"only {count[0]} of {messages} messages arrived")
        rate = messages / (time.perf_counter() - t0)
    return float(np.median(rtt)), float(np.percentile(rtt, 99)), rate


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=2000)
    ap.add_argument("--messages", type=int, default=50000)
    args = ap.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        # plain default
        port = _port()
        plain_router = {"mode": "router", "listen": {"endpoints": [f"tcp/127.0.0.1:{port}"]},
                        "scouting": {"multicast": {"enabled": False}}}
        (root / "plain.json5").write_text(json.dumps(plain_router))
        plain_client = {"mode": "client", "connect": {"endpoints": [f"tcp/127.0.0.1:{port}"]},
                        "scouting": {"multicast": {"enabled": False}}}
        r = _start(root / "plain.json5")
        try:
            rows.append(("plain tcp, no auth, no ACL", *_measure(plain_client, plain_client, args.rounds, args.messages)))
        finally:
            _stop(r)
        # secured
        make_dev_certs(root / "certs", hosts=("localhost",), days=1)
        write_credentials(root / "cred.txt", {"anchor-uav1": "a-secret", "emulator": "e-secret"})
        (root / "p.toml").write_text('anchors = ["uav1"]\ndictionary_file = "cred.txt"\n[users]\nemulator = "emulator"\n')
        prof = load_profile(root / "p.toml")
        port = _port()
        render_profile(prof, root / "zenoh", listen=[f"tls/127.0.0.1:{port}"], connect=[f"tls/localhost:{port}"])
        r = _start(root / "zenoh" / "router.json5")
        try:
            emu = client_config(prof, "emulator", connect=[f"tls/localhost:{port}"])
            anc = client_config(prof, "anchor-uav1", connect=[f"tls/localhost:{port}"])
            rows.append(("TLS + user/password + ACL", *_measure(emu, anc, args.rounds, args.messages)))
        finally:
            _stop(r)
    print(f"{'transport':28s} {'RTT median [us]':>16s} {'RTT p99 [us]':>13s} {'throughput [msg/s]':>19s}")
    for name, med, p99, rate in rows:
        print(f"{name:28s} {med:16.0f} {p99:13.0f} {rate:19.0f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
