"""Zenoh transport security: TLS + user/password + access control (diffpos_services.bus.security).

The bus tests start a real zenoh router (Python, router mode) in a subprocess with the
rendered router configuration on a free loopback TLS port; certificates and passwords are
generated into tmp_path at test time. Synchronisation uses the router's READY line and
publishers' matching status; negative checks ("X is NOT delivered") rely on ordering: the
forbidden put is sent first, an allowed put on the same session afterwards, and when the
allowed one arrives the forbidden one must not have (one transport link is FIFO).
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import get_args

import pytest
from diffpos_services.bus.security.acl import acl_config
from diffpos_services.bus.security.certs import make_dev_certs
from diffpos_services.bus.security.configs import (
    client_config,
    insecure_transport_warning,
    router_config,
    session_config,
    to_zenoh,
)
from diffpos_services.bus.security.credentials import read_credentials, write_credentials
from diffpos_services.bus.security.per_run import per_run_profile
from diffpos_services.bus.security.profile import (
    SecurityError,
    SecurityProfile,
    anchor_user,
    load_profile,
    profile_from_dict,
)
from diffpos_services.bus.security.render import check_profile, render_profile
from diffpos_services.bus.session import wait_matching
from diffpos_services.processes import free_tcp_port
from diffpos_services.wire.keys import KeyKind, Keys, parse_key

zenoh = pytest.importorskip("zenoh")

REPO = Path(__file__).resolve().parents[2]
SITE = "demo"
K = Keys(SITE)
WAIT_S = 10.0  # upper bound of every event wait [s]; a pass returns as soon as it happens

ROUTER_SCRIPT = """
import sys, zenoh
cfg = zenoh.Config.from_file(sys.argv[1])
with zenoh.open(cfg) as s:
    print("READY", s.zid(), flush=True)
    sys.stdin.read()  # until the test closes our stdin (or kills the process group)
"""


# ----------------------------------------------------------------------------- fixtures
def _write_profile(root: Path, *, mtls: bool = False) -> SecurityProfile:
    clients = ["anchor-uav1", "anchor-uav2", "fusion", "recorder", "dashboard", "emulator"] if mtls else []
    make_dev_certs(root / "certs", hosts=("localhost", "127.0.0.1"), clients=clients, days=2)
    write_credentials(root / "credentials.txt", {
        "anchor-uav1": "pw-uav1-secret", "anchor-uav2": "pw-uav2-secret", "fusion": "pw-fusion-secret",
        "recorder": "pw-recorder-secret", "dashboard": "pw-dash-secret", "emulator": "pw-emu-secret",
    })
    text = (
        f'site = "{SITE}"\nanchors = ["uav1", "uav2"]\ndictionary_file = "credentials.txt"\n'
        f"mtls = {'true' if mtls else 'false'}\n"
        'listen = ["tls/127.0.0.1:7447"]\nconnect = ["tls/localhost:7447"]\n'
        '[users]\nfusion = "fusion"\nrecorder = "recorder"\ndashboard = "dashboard"\nemulator = "emulator"\n'
    )
    (root / "profile.toml").write_text(text)
    profile = load_profile(root / "profile.toml")
    assert check_profile(profile) == []
    return profile


class Bus:
    """A running secured router subprocess and helpers to open client sessions."""

    def __init__(self, root: Path, *, mtls: bool = False) -> None:
        self.profile = _write_profile(root, mtls=mtls)
        self.port = free_tcp_port()
        # the router runs from the rendered json5 file, exactly as zenohd -c / docker-compose would
        render_profile(self.profile, root / "zenoh", listen=[f"tls/127.0.0.1:{self.port}"],
                          connect=[f"tls/localhost:{self.port}"])
        path = root / "zenoh" / "router.json5"
        self.proc = subprocess.Popen(
            [sys.executable, "-c", ROUTER_SCRIPT, str(path)],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
            text=True, start_new_session=True,
        )
        line = self.proc.stdout.readline()  # blocks until the router is listening (or dies)
        if not line.startswith("READY"):
            self.close()
            raise RuntimeError(f"router did not start: {line!r} {self.proc.stderr.read()[-2000:]}")

    def config(self, user: str, *, timeout_ms: int = 5000, **overrides) -> dict:
        return client_config(self.profile, user, connect=[f"tls/localhost:{self.port}"],
                                connect_timeout_ms=timeout_ms, **overrides)

    def open(self, user: str, **kw):
        return zenoh.open(to_zenoh(self.config(user, **kw)))

    def close(self) -> None:
        try:
            self.proc.stdin.close()
            self.proc.wait(timeout=5)
        except (subprocess.TimeoutExpired, OSError, ValueError):
            pass
        if self.proc.poll() is None:
            try:
                os.killpg(self.proc.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            self.proc.wait(timeout=5)


@pytest.fixture(scope="module")
def bus(tmp_path_factory):
    b = Bus(tmp_path_factory.mktemp("secure_bus"))
    yield b
    b.close()


class Collector:
    """Subscriber callback recording keys; an event fires when ``sentinel`` arrives."""

    def __init__(self, sentinel: str) -> None:
        self.keys: list[str] = []
        self.sentinel = sentinel
        self.done = threading.Event()
        self.lock = threading.Lock()

    def __call__(self, sample) -> None:
        with self.lock:
            self.keys.append(str(sample.key_expr))
        if str(sample.key_expr) == self.sentinel:
            self.done.set()

    def snapshot(self) -> list[str]:
        with self.lock:
            return list(self.keys)


def _wait_matching(pub) -> None:
    """Wait until the router has told ``pub`` that a subscriber matches (no sleeps)."""
    assert wait_matching(pub, timeout_s=WAIT_S), f"no matching subscriber for {pub.key_expr}"


def _refused(cfg: dict) -> bool:
    try:
        with zenoh.open(to_zenoh(cfg)):
            return False
    except zenoh.ZError:
        return True


def _check_forbidden_then_allowed(bus: Bus, *, sender: str, forbidden: list[str], allowed: str,
                                  observer: str = "recorder") -> list[str]:
    """Send every forbidden key, then the allowed one; return what ``observer`` received.

    Each forbidden publisher first waits for its matching status, so the put really leaves
    the sender (clients drop puts nobody subscribes to): a non-delivery is the router's doing.
    """
    got = Collector(allowed)
    with bus.open(observer) as obs, bus.open(sender) as snd:
        obs.declare_subscriber(K.everything(), got)
        bad = [snd.declare_publisher(k, congestion_control=zenoh.CongestionControl.BLOCK) for k in forbidden]
        good = snd.declare_publisher(allowed, congestion_control=zenoh.CongestionControl.BLOCK)
        for p in [*bad, good]:
            _wait_matching(p)
        for p in bad:
            p.put(b'{"forged": true}')
        good.put(b"{}")
        assert got.done.wait(WAIT_S), f"{sender}'s allowed put on {allowed} never arrived"
        return got.snapshot()


# ----------------------------------------------------------------------------- authentication
def test_authenticated_anchor_publishes_its_ranges_and_state(bus):
    keys = [K.anchor_state("uav1"), K.anchor_range("uav1", "n01")]
    got = _check_forbidden_then_allowed(bus, sender="anchor-uav1", forbidden=[], allowed=keys[1])
    assert got == [keys[1]]
    got = _check_forbidden_then_allowed(bus, sender="anchor-uav1", forbidden=[], allowed=keys[0])
    assert got == [keys[0]]


def test_unauthenticated_client_is_refused(bus):
    cfg = bus.config("recorder", timeout_ms=500)
    del cfg["transport"]["auth"]  # TLS only, no credentials
    assert _refused(cfg)
    cfg["mode"] = "peer"  # a peer gets no further
    assert _refused(cfg)
    # plain tcp to the TLS port: no session either
    plain = {"mode": "client", "connect": {"endpoints": [f"tcp/127.0.0.1:{bus.port}"], "timeout_ms": 500},
             "scouting": {"multicast": {"enabled": False}}}
    assert _refused(plain)
    # the same client with its credentials does connect (the refusal is the missing login)
    with bus.open("recorder", timeout_ms=5000):
        pass


def test_wrong_password_and_unknown_user_are_refused(bus):
    assert _refused(bus.config("anchor-uav1", timeout_ms=500, password="pw-uav2-secret"))
    cfg = bus.config("anchor-uav1", timeout_ms=500)
    cfg["transport"]["auth"]["usrpwd"] = {"user": "anchor-uav9", "password": "pw-uav1-secret"}
    assert _refused(cfg)


def test_client_rejects_router_certificate_from_another_ca(bus, tmp_path):
    other = make_dev_certs(tmp_path / "other", hosts=("localhost",), days=1)
    cfg = bus.config("recorder", timeout_ms=500)
    cfg["transport"]["link"]["tls"]["root_ca_certificate"] = str(other["ca"])
    assert _refused(cfg)


# ----------------------------------------------------------------------------- access control
def test_anchor_cannot_publish_estimates_or_spoof_another_anchor(bus):
    forbidden = [
        K.node_estimate("n01"),               # rogue estimate
        K.fusion_diagnostics(),
        K.anchor_range("uav2", "n01"),        # spoofing anchor uav2
        K.anchor_state("uav2"),
        K.truth_node("n01"),
        K.run_control(),
    ]
    allowed = K.anchor_range("uav1", "n02")
    got = _check_forbidden_then_allowed(bus, sender="anchor-uav1", forbidden=forbidden, allowed=allowed)
    assert got == [allowed], f"forbidden puts were delivered: {got[:-1]}"


def test_only_fusion_publishes_estimates(bus):
    est = K.node_estimate("n01")
    got = _check_forbidden_then_allowed(bus, sender="fusion", forbidden=[K.anchor_range("uav1", "n01"),
                                        K.anchor_state("uav2"), K.truth_node("n01")], allowed=est)
    assert got == [est]
    diag = K.fusion_diagnostics()
    got = _check_forbidden_then_allowed(bus, sender="fusion", forbidden=[], allowed=diag, observer="dashboard")
    assert got == [diag]


def test_readers_cannot_publish(bus):
    """Recorder and dashboard puts into the site prefix are dropped by the router.

    Ordering: the reader's forbidden puts, then on the same link a subscriber declaration
    on a sync key; only once the router has processed that declaration (after the puts) does
    the emulator's sync publisher match, and only then does the emulator send the put the
    observer waits for. So a forwarded forbidden put would reach the observer first.
    """
    sync_key = K.truth_anchor("sync")
    final = K.truth_node("n01")
    forbidden = [K.node_estimate("n01"), K.anchor_range("uav1", "n01"), K.truth_node("n02")]
    for reader, observer in (("recorder", "dashboard"), ("dashboard", "recorder")):
        got = Collector(final)
        with bus.open(observer) as obs, bus.open("emulator") as emu, bus.open(reader) as rd:
            for k in (K.node_estimate("*"), K.anchor_ranges(), K.truth_node("*")):
                obs.declare_subscriber(k, got)
            p_final = emu.declare_publisher(final, congestion_control=zenoh.CongestionControl.BLOCK)
            p_sync = emu.declare_publisher(sync_key, congestion_control=zenoh.CongestionControl.BLOCK)
            _wait_matching(p_final)
            assert not p_sync.matching_status.matching
            bad = [rd.declare_publisher(k, congestion_control=zenoh.CongestionControl.BLOCK) for k in forbidden]
            for p in bad:
                _wait_matching(p)  # the put really leaves the reader
                p.put(b'{"forged": true}')
            rd.declare_subscriber(sync_key, lambda s: None)
            _wait_matching(p_sync)
            p_final.put(b"{}")
            assert got.done.wait(WAIT_S)
            assert got.snapshot() == [final], f"{reader}'s puts were delivered"


def test_fusion_never_receives_truth(bus):
    """Fusion's catch-all subscription is refused; only its anchor inputs are routed to it.

    Ordering: the truth put reaches the recorder (so the router has already forwarded it to
    every matching subscriber) before the anchor sends the state fusion waits for.
    """
    truth, state = K.truth_node("n01"), K.anchor_state("uav1")
    got, got_all = Collector(state), Collector(state)
    rec_got = Collector(truth)
    with (bus.open("fusion") as fus, bus.open("recorder") as rec, bus.open("emulator") as emu,
          bus.open("anchor-uav1") as anc):
        fus.declare_subscriber(K.everything(), got_all)  # refused by the router (ingress)
        for k in K.fusion_inputs():
            fus.declare_subscriber(k, got)
        rec.declare_subscriber(K.everything(), rec_got)
        p_truth = emu.declare_publisher(truth, congestion_control=zenoh.CongestionControl.BLOCK)
        p_state = anc.declare_publisher(state, congestion_control=zenoh.CongestionControl.BLOCK)
        _wait_matching(p_truth)
        _wait_matching(p_state)
        p_truth.put(b"{}")
        assert rec_got.done.wait(WAIT_S)
        p_state.put(b"{}")
        # the state arrives and is handed locally to both fusion subscribers; the truth never
        assert got.done.wait(WAIT_S) and got_all.done.wait(WAIT_S)
        assert got.snapshot() == [state]
        assert got_all.snapshot() == [state]


def test_liveliness_tokens_only_for_own_anchor(bus):
    seen: list[tuple[str, bool]] = []
    ev = threading.Event()
    legit = K.alive_anchor("uav1")

    def on_token(sample) -> None:
        seen.append((str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT))
        if str(sample.key_expr) == legit:
            ev.set()

    with bus.open("fusion") as fus, bus.open("anchor-uav1") as anc:
        spoof = anc.liveliness().declare_token(K.alive_anchor("uav2"))  # denied
        fake_fusion = anc.liveliness().declare_token(K.alive_fusion())  # denied
        token = anc.liveliness().declare_token(legit)
        sub = fus.liveliness().declare_subscriber(K.alive_anchors(), on_token, history=True)
        assert ev.wait(WAIT_S), "the anchor's own liveliness token was not seen"
        assert [k for k, _ in seen] == [legit]
        del spoof, fake_fusion, token, sub


def test_mtls_requires_client_certificate(tmp_path):
    b = Bus(tmp_path, mtls=True)
    try:
        with b.open("recorder", timeout_ms=5000):
            pass
        cfg = b.config("recorder", timeout_ms=500)
        tls = cfg["transport"]["link"]["tls"]
        del tls["connect_certificate"], tls["connect_private_key"]
        assert _refused(cfg)
    finally:
        b.close()


# ----------------------------------------------------------------------------- ACL model
def _acl_allows(acl: dict, user: str, message: str, flow: str, key: str) -> bool:
    """Reference evaluation of a default-deny, allow-only ACL with zenoh's key inclusion."""
    subjects = {s["id"] for s in acl["subjects"] if user in s.get("usernames", [])}
    rule_ids = {r for p in acl["policies"] if subjects & set(p["subjects"]) for r in p["rules"]}
    for r in acl["rules"]:
        if r["id"] in rule_ids and message in r["messages"] and flow in r.get("flows", ["ingress", "egress"]):
            if any(zenoh.KeyExpr(k).includes(zenoh.KeyExpr(key)) for k in r["key_exprs"]):
                return True
    return False


def test_acl_publish_matrix_matches_key_table(tmp_path):
    """Who may put each key, from the ACL, equals the publisher column of keys.py's table."""
    profile = profile_from_dict({"site": "*", "anchors": ["uav1", "uav2"], "users": {
        "fusion": "fusion", "recorder": "recorder", "dashboard": "dashboard", "emulator": "emulator"}},
        root=tmp_path)
    acl = acl_config(profile)
    assert acl["default_permission"] == "deny" and acl["enabled"] is True
    users = sorted(profile.identities())
    for site in ("demo", "paper"):
        k = Keys(site)
        keys = [k.anchor_state("uav1"), k.anchor_state("uav2"), k.anchor_range("uav1", "n1"),
                k.anchor_range("uav2", "n7"), k.node_estimate("n1"), k.fusion_diagnostics(),
                k.anchor_range_batch("uav1"), k.anchor_range_batch("uav2"),
                k.truth_node("n1"), k.truth_anchor("uav1"), k.run_control(), k.run_clock(),
                k.heartbeat("fusion"), k.heartbeat("recorder"), k.heartbeat("dashboard"),
                k.heartbeat("anchor", "uav1"), k.heartbeat("anchor", "uav2")]
        alive = [(k.alive_anchor("uav1"), "anchor-uav1"), (k.alive_anchor("uav2"), "anchor-uav2"),
                 (k.alive_fusion(), "fusion"), (k.alive_recorder(), "recorder"),
                 (k.alive_dashboard(), "dashboard")]
        # every kind of key of keys.py's table is covered (a new key needs its ACL rule)
        assert {parse_key(x).kind for x in [*keys, *(t for t, _ in alive)]} == set(get_args(KeyKind))
        for key in keys:
            pk = parse_key(key)
            beat = ({anchor_user(pk.anchor_id or "")} if pk.service == "anchor"
                    else {pk.service or ""})
            expected = {
                "heartbeat": beat,
                "anchor_state": {anchor_user(pk.anchor_id or "")},
                "range": {anchor_user(pk.anchor_id or "")},
                "range_batch": {anchor_user(pk.anchor_id or "")},
                "estimate": {"fusion"}, "diagnostics": {"fusion"},
                "truth_node": {"emulator"}, "truth_anchor": {"emulator"}, "run_control": {"emulator"},
                "run_clock": {"emulator"},
            }[pk.kind]
            got = {u for u in users if _acl_allows(acl, u, "put", "ingress", key)}
            assert got == expected, key
        for key, owner in alive:
            assert {u for u in users if _acl_allows(acl, u, "liveliness_token", "ingress", key)} == {owner}
        # anchors receive the run's start gate and lockstep clock
        for a in ("uav1", "uav2"):
            for key in (k.run_control(), k.run_clock()):
                assert _acl_allows(acl, anchor_user(a), "declare_subscriber", "ingress", key)
                assert _acl_allows(acl, anchor_user(a), "put", "egress", key)
        # fusion reads anchors, never truth; readers read everything
        assert _acl_allows(acl, "fusion", "put", "egress", k.anchor_range("uav2", "n1"))
        assert not _acl_allows(acl, "fusion", "put", "egress", k.truth_node("n1"))
        assert not _acl_allows(acl, "fusion", "declare_subscriber", "ingress", k.everything())
        for reader in ("recorder", "dashboard", "emulator"):
            assert _acl_allows(acl, reader, "declare_subscriber", "ingress", k.everything())
            assert _acl_allows(acl, reader, "put", "egress", k.anchor_range("uav1", "n1"))
    # nothing outside the diffpos prefix, for anyone
    assert not any(_acl_allows(acl, u, m, "ingress", "other/thing") for u in users
                   for m in ("put", "declare_subscriber", "liveliness_token", "query"))


# ----------------------------------------------------------------------------- files, validation
def test_committed_configs_match_dev_profile(tmp_path):
    """security/zenoh/*.json5 are exactly what the dev profile renders (no hand edits)."""
    profile = load_profile(REPO / "security" / "profile.dev.toml")
    written = render_profile(profile, tmp_path, base_dir="/security")
    committed = REPO / "security" / "zenoh"
    assert sorted(p.name for p in written) == sorted(p.name for p in committed.glob("*.json5"))
    for p in written:
        assert p.read_text() == (committed / p.name).read_text(), p.name
        zenoh.Config.from_file(str(committed / p.name))  # zenoh parses it
    assert check_profile(profile) == []


def test_insecure_transport_warning():
    plain = {"mode": "client", "connect": {"endpoints": ["tcp/127.0.0.1:7447"]}}
    msg = insecure_transport_warning(plain)
    assert msg is not None and "UNAUTHENTICATED" in msg and "tcp/127.0.0.1:7447" in msg
    assert not msg.startswith("NOT loopback")
    wide = {"mode": "router", "listen": {"endpoints": ["tcp/0.0.0.0:7447"]}}
    assert insecure_transport_warning(wide).startswith("NOT loopback")
    # zenoh's per-mode default: a router without explicit listen endpoints opens tcp/[::]:7447
    default_router = {"mode": "router", "listen": {"endpoints": {"router": ["tcp/[::]:7447"], "peer": []}}}
    assert insecure_transport_warning(default_router).startswith("NOT loopback")
    client_listen = {"mode": "client", "connect": {"endpoints": ["tcp/[::1]:7447"]},
                     "listen": {"endpoints": {"router": ["tcp/[::]:7447"]}}}  # ignored by clients
    assert not insecure_transport_warning(client_listen).startswith("NOT loopback")
    tls_only = {"connect": {"endpoints": ["tls/router:7447"]}}
    assert insecure_transport_warning(tls_only) is not None  # encrypted but anyone can log in
    profile = load_profile(REPO / "security" / "profile.dev.toml")
    assert insecure_transport_warning(client_config(profile, "fusion")) is None
    assert insecure_transport_warning(router_config(profile)) is None


@pytest.mark.parametrize(("raw", "field"), [
    ({"site": "a/b"}, "site"),
    ({"anchors": ["uav 1"]}, "anchors"),
    ({"anchors": ["uav1", "uav1"]}, "twice"),
    ({"users": {"pilot": "x"}}, "users.pilot"),
    ({"users": {"fusion": "a:b"}}, "users.fusion"),
    ({"users": {"fusion": "anchor-uav1"}, "anchors": ["uav1"]}, "more than one identity"),
    ({"listen": ["tcp/0.0.0.0:7447"]}, "not encrypted"),
    ({"connect": ["tls/router"]}, "connect"),
    ({"mtls": "yes"}, "mtls"),
    ({"passwords": {}}, "unknown field"),
])
def test_profile_errors_name_the_field(tmp_path, raw, field):
    with pytest.raises(SecurityError, match=field):
        profile_from_dict(raw, root=tmp_path)


@pytest.mark.parametrize(("text", "what"), [
    ("# comment\nfusion:pw\n", "line 1"),
    ("fusion:pw\n\n", "line 2"),
    ("fusion\n", "user:password"),
    ("fusion:a\nfusion:b\n", "twice"),
    ("fu sion:pw\n", "user"),
])
def test_credentials_file_validation(tmp_path, text, what):
    p = tmp_path / "c.txt"
    p.write_text(text)
    with pytest.raises(SecurityError, match=what):
        read_credentials(p)


def test_credentials_round_trip_keeps_colons(tmp_path):
    creds = {"fusion": "a:b:c", "anchor-uav1": "x"}
    p = write_credentials(tmp_path / "c.txt", creds)
    assert read_credentials(p) == creds
    assert (p.stat().st_mode & 0o777) == 0o600


def test_dev_certs_have_router_names(tmp_path):
    paths = make_dev_certs(tmp_path, hosts=("router", "127.0.0.1"), clients=("fusion",), days=3,
                              backend="openssl")
    out = subprocess.run(["openssl", "x509", "-in", str(paths["router"]), "-noout", "-text"],
                         capture_output=True, text=True, check=True).stdout
    assert "DNS:router" in out and "IP Address:127.0.0.1" in out and "DEV ONLY" in out
    for k in ("ca_key", "router_key", "client_key:fusion"):
        assert (paths[k].stat().st_mode & 0o777) == 0o600
    v = subprocess.run(["openssl", "verify", "-CAfile", str(paths["ca"]), str(paths["router"]),
                        str(paths["client:fusion"])], capture_output=True, text=True)
    assert v.returncode == 0, v.stderr


# ----------------------------------------------------------------------------- service entry point
def test_session_config_fallback_warns_and_file_does_not(bus, tmp_path):
    """What a service does with and without --zenoh-config, end to end through the router."""
    plain = {"mode": "client", "connect": {"endpoints": ["tcp/127.0.0.1:7447"]}}
    _, warning = session_config(None, fallback=plain)
    assert warning is not None and "UNAUTHENTICATED" in warning
    # a rendered client file (absolute paths of this machine, the bus's port) opens a session
    written = render_profile(bus.profile, tmp_path / "zenoh", connect=[f"tls/localhost:{bus.port}"],
                                listen=[f"tls/127.0.0.1:{bus.port}"], connect_timeout_ms=5000)
    assert {p.name for p in written} == {"router.json5", "anchor-uav1.json5", "anchor-uav2.json5",
                                         "fusion.json5", "recorder.json5", "dashboard.json5", "emulator.json5"}
    cfg, warning = session_config(tmp_path / "zenoh" / "fusion.json5")
    assert warning is None
    got = Collector(K.node_estimate("n05"))
    with bus.open("recorder") as rec, zenoh.open(cfg) as fus:
        rec.declare_subscriber(K.everything(), got)
        pub = fus.declare_publisher(K.node_estimate("n05"), congestion_control=zenoh.CongestionControl.BLOCK)
        _wait_matching(pub)
        pub.put(b"{}")
        assert got.done.wait(WAIT_S)
    # an explicit --connect replaces the file's endpoints
    cfg, _ = session_config(tmp_path / "zenoh" / "fusion.json5", connect=["tls/other:7447"])
    assert json.loads(cfg.get_json("connect/endpoints")) == ["tls/other:7447"]


def test_session_config_errors_name_the_file(tmp_path):
    with pytest.raises(SecurityError, match="file not found"):
        session_config(tmp_path / "missing.json5")
    bad = tmp_path / "bad.json5"
    bad.write_text('{ mode: "client", transport: { link: { tls: { nonsense_key: 1 } } } }')
    with pytest.raises(SecurityError, match=r"bad\.json5"):
        session_config(bad)
    # the committed docker files point at /security/...: outside a container that is reported
    if not Path("/security/certs/ca.pem").exists():
        with pytest.raises(SecurityError, match="root_ca_certificate"):
            session_config(REPO / "security" / "zenoh" / "fusion.json5")


def test_ca_bundle_allows_overlapping_rotation(bus, tmp_path):
    """A root_ca_certificate file holding the next CA and the current one still connects."""
    nxt = make_dev_certs(tmp_path / "next", hosts=("localhost",), days=1)
    bundle = tmp_path / "bundle.pem"
    bundle.write_text(Path(nxt["ca"]).read_text() + Path(bus.profile.path(bus.profile.ca_certificate)).read_text())
    cfg = bus.config("recorder", timeout_ms=5000)
    cfg["transport"]["link"]["tls"]["root_ca_certificate"] = str(bundle)
    assert not _refused(cfg)


def test_per_run_profile_fresh_secrets_in_a_private_folder(tmp_path):
    """What `diffpos emulate --security-profile` runs with: the profile's identities with
    fresh passwords and certificates (client certificates with mTLS), the CA key deleted;
    another run gets other secrets; a folder other users may enter is refused."""
    dev = load_profile(REPO / "security" / "profile.dev.toml")
    dev_pw = read_credentials(dev.path(dev.dictionary_file))
    runs = []
    for name, mtls in (("run1", True), ("run2", False)):
        out = tmp_path / name
        out.mkdir()
        os.chmod(out, 0o700)
        run = per_run_profile(dataclasses.replace(dev, mtls=mtls), out,
                                 hosts=["localhost", "127.0.0.1", "localhost"])
        assert run.root == out and run.identities() == dev.identities() and run.mtls == mtls
        assert check_profile(run) == []  # every file it names exists (mTLS: client certs)
        assert not (out / "certs" / "ca.key").exists()
        assert Path(run.path(run.ca_certificate)).read_bytes() != \
            Path(dev.path(dev.ca_certificate)).read_bytes()
        pw = read_credentials(run.path(run.dictionary_file))
        assert set(pw) == set(dev_pw) and all(len(p) >= 32 for p in pw.values())
        assert not set(pw.values()) & set(dev_pw.values())
        assert Path(run.path(run.dictionary_file)).stat().st_mode & 0o077 == 0
        runs.append(pw)
    assert not set(runs[0].values()) & set(runs[1].values())
    shared = tmp_path / "shared"
    shared.mkdir()
    os.chmod(shared, 0o755)
    with pytest.raises(SecurityError, match="0700"):
        per_run_profile(dev, shared, hosts=["localhost"])
    assert list(shared.iterdir()) == []  # nothing written there


def test_make_dev_certs_script_and_password_rotation(tmp_path):
    """security/make_dev_certs.py writes certificates; --new-passwords rotates and re-renders."""

    for name in ("profile.dev.toml", "credentials.dev.txt"):
        shutil.copy(REPO / "security" / name, tmp_path / name)
    old = read_credentials(tmp_path / "credentials.dev.txt")
    r = subprocess.run([sys.executable, str(REPO / "security" / "make_dev_certs.py"), "--out",
                        str(tmp_path / "certs"), "--days", "1", "--client", "fusion", "--new-passwords",
                        "--profile", str(tmp_path / "profile.dev.toml")], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert "DEV ONLY" in r.stdout
    for f in ("ca.pem", "ca.key", "router.pem", "router.key", "clients/fusion.pem", "clients/fusion.key"):
        assert (tmp_path / "certs" / f).is_file(), f
    new = read_credentials(tmp_path / "credentials.dev.txt")
    assert new.keys() == old.keys() and all(new[u] != old[u] for u in new)
    fusion = (tmp_path / "zenoh" / "fusion.json5").read_text()
    assert new["fusion"] in fusion and "/security/certs/ca.pem" in fusion


def test_plain_endpoint_overrides_are_refused(tmp_path):
    profile = profile_from_dict({"anchors": ["uav1"]}, root=tmp_path)
    with pytest.raises(SecurityError, match=r"listen.*not encrypted"):
        router_config(profile, listen=["tcp/0.0.0.0:7447"])
    with pytest.raises(SecurityError, match=r"connect.*not encrypted"):
        client_config(profile, "anchor-uav1", password="x", connect=["tcp/router:7447"])


def _alive(session, key: str) -> bool:
    """What the container health check does: a liveliness query for ``key``."""
    return any(r.ok is not None for r in session.liveliness().get(key, timeout=WAIT_S))


def _alive_soon(session, key: str) -> bool:
    """:func:`_alive` asked again until it holds or ``WAIT_S`` passed: a token declared a
    moment ago reaches the router asynchronously (an empty answer before it does)."""
    deadline = time.monotonic() + WAIT_S
    while True:
        if _alive(session, key):
            return True
        if time.monotonic() > deadline:
            return False


def test_health_check_liveliness_query_per_identity(bus):
    """Each container checks its own token with its own identity (a second session)."""
    with bus.open("anchor-uav1") as anc, bus.open("anchor-uav2") as anc2, bus.open("fusion") as fus:
        tok1 = anc.liveliness().declare_token(K.alive_anchor("uav1"))
        tok2 = anc2.liveliness().declare_token(K.alive_anchor("uav2"))
        tokf = fus.liveliness().declare_token(K.alive_fusion())
        with bus.open("recorder") as probe:  # the recorder's container checks the fusion
            assert _alive_soon(probe, K.alive_fusion())
            assert _alive_soon(probe, K.alive_anchor("uav2"))  # (so the router has it too)
        with bus.open("anchor-uav1") as probe:
            assert _alive_soon(probe, K.alive_anchor("uav1"))
            assert not _alive(probe, K.alive_anchor("uav2"))  # an anchor sees only its own token
        with bus.open("fusion") as probe:
            assert _alive_soon(probe, K.alive_fusion())
        del tok1, tok2, tokf


# ----------------------------------------------------------------------------- docker-compose
def _load_yaml(path: Path) -> dict:
    """PyYAML (with Compose's ``!override`` tag: the tagged value replaces the base one)."""
    yaml = pytest.importorskip("yaml")

    class ComposeLoader(yaml.SafeLoader):
        pass

    def _override(loader, node):
        if isinstance(node, yaml.SequenceNode):
            return loader.construct_sequence(node, deep=True)
        if isinstance(node, yaml.MappingNode):
            return loader.construct_mapping(node, deep=True)
        return loader.construct_scalar(node)

    ComposeLoader.add_constructor("!override", _override)
    return yaml.load(path.read_text(), Loader=ComposeLoader)


def _strip_connect(argv: list[str]) -> list[str]:
    out, skip = [], False
    for a in argv:
        if skip:
            skip = False
        elif a == "--connect":
            skip = True
        else:
            out.append(a)
    return out


def _zenoh_file(argv: list[str]) -> str:
    assert "--connect" not in argv, argv
    return argv[argv.index("--zenoh-config") + 1]


def test_secure_compose_override_matches_base_and_profile():
    base_path = REPO / "docker-compose.yml"
    if not base_path.exists():
        pytest.skip("no docker-compose.yml yet")
    base = _load_yaml(base_path)["services"]
    over = _load_yaml(REPO / "security" / "docker-compose.secure.yml")["services"]
    profile = load_profile(REPO / "security" / "profile.dev.toml")
    ids = profile.identities()
    assert set(over) == set(base)
    # router: the rendered router file from the mounted security folder
    assert "./security:/security:ro" in over["router"]["volumes"]
    assert over["router"]["command"] == ["-c", "/security/zenoh/router.json5"]
    for name, svc in base.items():
        if name == "router":
            continue
        o = over[name]
        assert "./security:/security:ro" in o["volumes"], name
        cfg = _zenoh_file(o["command"])
        user = Path(cfg).stem
        assert cfg == f"/security/zenoh/{user}.json5" and (REPO / "security" / "zenoh" / f"{user}.json5").is_file()
        role, anchor_id = ids[user]
        assert role == name.split("-")[0], (name, user)
        if anchor_id is not None:
            assert o["command"][o["command"].index("--id") + 1] == anchor_id
        # the same command as the base file, with --connect replaced by --zenoh-config
        assert _strip_connect(svc["command"]) == [a for a in o["command"] if a not in ("--zenoh-config", cfg)]
        site = o["command"][o["command"].index("--site") + 1]
        assert profile.site in ("*", site)
        # health checks run with the service's own identity
        test = (svc.get("healthcheck") or {}).get("test", [])
        if "health" in test:
            otest = o["healthcheck"]["test"]
            assert _zenoh_file(otest) == cfg
            assert _strip_connect(test) == [a for a in otest if a not in ("--zenoh-config", cfg)]
    # the rendered client files dial the compose router by the name in its certificate
    fusion = json.loads("\n".join(
        ln for ln in (REPO / "security" / "zenoh" / "fusion.json5").read_text().splitlines()
        if not ln.startswith("//")))
    assert fusion["connect"]["endpoints"] == ["tls/router:7447"]
    out = subprocess.run(["openssl", "x509", "-in", str(REPO / "security" / "certs" / "router.pem"),
                          "-noout", "-ext", "subjectAltName"], capture_output=True, text=True, check=True).stdout
    assert "DNS:router" in out
