"""`diffpos emulate --security-profile` end to end: every role of the secured bus (anchors,
fusion, recorder, dashboard, the orchestrator) gets what it needs from the access rules, and
the run uses fresh secrets of its own, never the committed dev passwords and certificates.

Real processes (the ``services`` fixture) on a TLS router with passwords and the default-deny
ACL; recordings are read back with ``mcap``'s reader, the dashboard's .rrd with Rerun's.
Synchronisation: the orchestrator's and the dashboard's log lines, and a subscriber of the
test that waits for the messages it needs; never sleeps.
"""

from __future__ import annotations

import collections
import json
import re
import signal
import threading
import time
from pathlib import Path

import pytest
from diffpos_services.bus.security.configs import client_config, to_zenoh
from diffpos_services.bus.security.credentials import read_credentials
from diffpos_services.bus.security.profile import load_profile
from diffpos_services.recording.reader import JsonDecoderFactory
from diffpos_services.wire.keys import Keys, parse_key, parse_recording_topic
from mcap.reader import make_reader

zenoh = pytest.importorskip("zenoh")

REPO = Path(__file__).resolve().parents[2]
PROFILE = REPO / "security" / "profile.dev.toml"
K = Keys("demo")  # emulate's default site
NODES = {f"r0{i}" for i in range(1, 7)}  # the default scenario's six responders
WAIT_S = 60.0  # upper bound of every wait [s]; a pass returns as soon as it happens


def _recorded(path: Path) -> collections.Counter:
    """Kind -> message count of a recording, read with mcap's own reader (needs a complete
    file: footer and summary); estimates are also counted per node (``estimate:<node>``)."""
    counts: collections.Counter = collections.Counter()
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[JsonDecoderFactory()])
        assert reader.get_summary() is not None, "no summary: the file was not closed"
        for _, channel, _, decoded in reader.iter_decoded_messages():
            pk = parse_recording_topic(channel.topic)
            assert pk is not None, channel.topic
            counts[pk.kind] += 1
            if pk.kind == "estimate":
                assert decoded["node_id"] == pk.node_id
                counts[f"estimate:{pk.node_id}"] += 1
    return counts


# ----------------------------------------------------------------------------- item 8
def test_secured_lockstep_emulate_records_and_reads_back(services, tmp_path):
    """The documented secured run with a recording (it timed out waiting for the recorder's
    liveliness token, which the ACL did not allow): exit 0, every epoch of every node
    estimated, and the recording holds those estimates, the ranges, the truth and the run
    control (the recorder reads everything it needs)."""
    mcap_path, summary_path = tmp_path / "run.mcap", tmp_path / "summary.json"
    p = services.start("emulate", "emulate", "--security-profile", str(PROFILE),
                       "--record", str(mcap_path), "--duration", "3", "--speed", "0",
                       "--dashboard", "off", "--json", str(summary_path), "--no-progress",
                       "--log-dir", str(tmp_path / "logs"))
    assert p.wait(timeout=180) == 0, services.log("emulate")[-3000:]
    s = json.loads(summary_path.read_text())
    assert s["secured"] is True and s["endpoint"].startswith("tls/localhost:")
    assert s["recording"] == str(mcap_path) and not s["lost"]
    assert s["estimates"] == len(NODES) * 30 and s["epochs_per_node_min"] == 30
    for f in (tmp_path / "logs").iterdir():
        text = f.read_text(errors="replace")
        assert "UNAUTHENTICATED" not in text and "login is refused" not in text, f.name
    got = _recorded(mcap_path)
    assert got["estimate"] == s["estimates"]  # fusion publishes with BLOCK; recorder awaited
    assert {k.split(":")[1] for k in got if k.startswith("estimate:")} == NODES
    assert got["range"] > 0 and got["anchor_state"] > 0 and got["diagnostics"] > 0
    assert got["truth_node"] > 0 and got["truth_anchor"] > 0 and got["run_control"] == 1
    assert got["liveliness"] > 0  # the recorder watched the tokens


# ----------------------------------------------------------------------------- item 9
def _wait_for(text_of, pattern: str, what: str, proc) -> re.Match:
    """Wait until ``pattern`` appears in ``text_of()`` (a log); fail if ``proc`` exits."""
    deadline = time.monotonic() + WAIT_S
    tick = threading.Event()
    while True:
        m = re.search(pattern, text_of())
        if m:
            return m
        assert proc.poll() is None, f"emulate exited ({proc.returncode}) before {what}"
        assert time.monotonic() < deadline, f"no {what} after {WAIT_S:.0f} s"
        tick.wait(0.1)  # a log file has no change notification: poll it


def _config(path: Path, *, timeout_ms: int, password: str | None = None):
    """A run's rendered client file, with a finite connect timeout (and another password)."""
    cfg = zenoh.Config.from_file(str(path))
    cfg.insert_json5("connect/timeout_ms", json.dumps(timeout_ms))
    if password is not None:
        cfg.insert_json5("transport/auth/usrpwd/password", json.dumps(password))
    return cfg


def _refused(cfg) -> bool:
    try:
        with zenoh.open(cfg):
            return False
    except zenoh.ZError:
        return True


class _Seen:
    """Subscriber callback: the set of (kind, node) seen; ``done`` once every node has both
    an estimate and a truth."""

    def __init__(self) -> None:
        self.seen: set[tuple[str, str]] = set()
        self.done = threading.Event()

    def __call__(self, sample) -> None:
        pk = parse_key(str(sample.key_expr))
        if pk is not None and pk.node_id is not None:
            self.seen.add((pk.kind, pk.node_id))
        if {n for k, n in self.seen if k == "estimate"} >= NODES and \
                {n for k, n in self.seen if k == "truth_node"} >= NODES:
            self.done.set()


def test_secured_emulate_uses_fresh_per_run_secrets(services, tmp_path):
    """The run's router accepts only the run's own secrets: the committed fusion password
    (with the run's CA, or the whole committed dev identity) is refused while the run's own
    files log in; the private folder holding them is 0700, keeps no CA key and is gone
    after the run. The recorder and the dashboard (save mode) get what they draw/record."""
    mcap_path, rrd_path, logs = tmp_path / "run.mcap", tmp_path / "run.rrd", tmp_path / "logs"
    p = services.start("emulate", "emulate", "--security-profile", str(PROFILE),
                       "--duration", "120", "--channel", "ideal", "--record", str(mcap_path),
                       "--dashboard", "save", str(rrd_path), "--no-progress",
                       "--log-dir", str(logs))
    log = lambda: services.log("emulate")  # noqa: E731
    secret_dir = Path(_wait_for(log, r"fresh passwords and certificates.* dir=(\S+)",
                                "per-run secrets", p).group(1))
    endpoint = _wait_for(log, r"all services ready .*endpoint=(\S+)", "ready", p).group(1)
    dev = load_profile(PROFILE)
    dev_pw = read_credentials(dev.path(dev.dictionary_file))
    fusion_file = secret_dir / "zenoh" / "fusion.json5"
    # the committed fusion password is refused, trusting the run's CA (only the password
    # differs from a file that logs in, below) or the committed CA (the dev identity as a whole)
    assert _refused(_config(fusion_file, timeout_ms=3000, password=dev_pw["fusion"])), \
        "the run's router accepts the committed fusion password"
    committed = client_config(dev, "fusion", connect=[endpoint], connect_timeout_ms=3000)
    assert _refused(to_zenoh(committed)), "the run's router accepts the committed identity"
    run_pw = read_credentials(secret_dir / "credentials.txt")
    assert set(run_pw) == set(dev_pw)
    reused = sorted(u for u, pw in run_pw.items() if pw in dev_pw.values())
    assert not reused, f"committed passwords reused for {reused}"
    assert secret_dir.stat().st_mode & 0o777 == 0o700
    assert fusion_file.stat().st_mode & 0o077 == 0
    assert not (secret_dir / "certs" / "ca.key").exists()  # nothing can be signed with it
    # the run's own (read-only) recorder identity logs in and reads what the dashboard draws
    _wait_for(lambda: (logs / "dashboard.log").read_text(), "dashboard subscribed",
              "dashboard subscription", p)
    seen = _Seen()
    with zenoh.open(_config(secret_dir / "zenoh" / "recorder.json5", timeout_ms=10000)) as s:
        subs = [s.declare_subscriber(k, seen) for k in (K.estimates(), K.truth_all())]
        assert seen.done.wait(WAIT_S), f"secured run published only {sorted(seen.seen)}"
        del subs
    services.kill("emulate", signal.SIGTERM)  # ends the run early, in order
    p.wait(timeout=60)
    assert not secret_dir.exists(), "the per-run secrets outlived the run"
    # the recorder recorded and the dashboard drew every node (their identities sufficed)
    got = _recorded(mcap_path)
    assert {k.split(":")[1] for k in got if k.startswith("estimate:")} == NODES
    convert = pytest.importorskip("diffpos_services.dashboard.convert")
    rows = convert.rrd_rows(rrd_path)
    for n in NODES:
        assert rows.get(f"/world/nodes/{n}/estimate"), f"dashboard drew no estimate of {n}"
        assert rows.get(f"/world/nodes/{n}/truth"), f"dashboard drew no truth of {n}"
    for f in logs.iterdir():
        assert "login is refused" not in f.read_text(errors="replace"), f.name
