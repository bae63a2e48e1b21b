"""Integrity on a bus without access control: whose messages are the run's own, and two
publishers under one key.

On the default (unsecured) bus any loopback process can publish on the run's keys. Two
defences that need no access control:

- **Signed publications** (:class:`Signer`, :class:`Verifier`). ``diffpos emulate`` hands
  its services a per-run secret token in the environment (:data:`RUN_TOKEN_ENV`, never on a
  command line, in a message or in a recording). A service with a token attaches to each
  publication its zenoh id (16 bytes) and an HMAC-SHA256 (first 16 bytes) of that id, the
  key and the payload under the token. A subscriber with the token accepts a publication as
  the run's own only if the MAC is right and, for the fusion's publications, the sample's
  timestamp carries that same full zenoh id (the fusion stamps its samples): a copy
  republished by another session, or a forged estimate, fails; a prefix of the id that any
  subscriber reads from an estimate proves nothing any more.
- **One publisher per anchor key** (:class:`PublisherGuard`). Every anchor attaches its
  process nonce (:func:`diffpos_services.bus.heartbeat.process_nonce`) to each message. A
  second nonce under the same anchor while the first is still publishing, or a sequence
  number that does not advance under one nonce (a copier that copies the nonce too), means
  two publishers: the anchor is *contested* and neither is trusted until only one has
  published for :data:`CONTEST_WINDOW_S`.
"""

from __future__ import annotations

import hashlib
import hmac
import os
import secrets
import threading
from dataclasses import dataclass, field
from typing import Any

__all__ = ["CONTEST_WINDOW_S", "RUN_TOKEN_ENV", "PublisherGuard", "Signer", "Verifier",
           "new_run_token", "run_token"]

#: environment variable holding the run's secret token (hex)
RUN_TOKEN_ENV = "DIFFPOS_RUN_TOKEN"
#: a contested anchor is trusted again once only one publisher was heard for this long [s]
CONTEST_WINDOW_S = 2.0
_MAC_BYTES = 16
_ZID_BYTES = 16


def new_run_token() -> str:
    """A fresh secret token (64 hex digits)."""
    return secrets.token_hex(32)


def run_token(env: dict[str, str] | None = None) -> bytes | None:
    """The run's token from :data:`RUN_TOKEN_ENV` (``None``: not set, nothing is signed)."""
    text = (os.environ if env is None else env).get(RUN_TOKEN_ENV, "")
    try:
        return bytes.fromhex(text) or None
    except ValueError:
        return text.encode() or None


def _zid_bytes(zid: str) -> bytes:
    """A zenoh id's text (hex, up to 32 digits) as 16 bytes."""
    return bytes.fromhex(zid.rjust(2 * _ZID_BYTES, "0"))[-_ZID_BYTES:]


def _mac(token: bytes, zid: bytes, key: str, payload: bytes) -> bytes:
    h = hmac.new(token, zid, hashlib.sha256)
    h.update(key.encode())
    h.update(b"\0")
    h.update(payload)
    return h.digest()[:_MAC_BYTES]


@dataclass(frozen=True)
class Signer:
    """Signs one session's publications (``token`` None: signs nothing)."""

    token: bytes | None
    zid: bytes

    @classmethod
    def for_session(cls, session: Any, token: bytes | None = None) -> Signer:
        token = run_token() if token is None else token
        if not token:
            return cls(None, b"")
        return cls(token, _zid_bytes(str(session.zid())))

    def attachment(self, key: str, payload: bytes) -> bytes | None:
        """What to attach to the publication of ``payload`` on ``key``."""
        if not self.token:
            return None
        return self.zid + _mac(self.token, self.zid, key, payload)


@dataclass(frozen=True)
class Verifier:
    """Decides whether a zenoh sample is the run's own (see the module docstring)."""

    token: bytes

    def ours(self, sample: Any, *, stamped: bool = True) -> bool:
        """True if ``sample`` carries a valid MAC under the token and (``stamped``) its
        timestamp names the same full zenoh id as the MAC."""
        att = sample.attachment
        if att is None:
            return False
        att = att.to_bytes()
        if len(att) != _ZID_BYTES + _MAC_BYTES:
            return False
        zid, mac = att[:_ZID_BYTES], att[_ZID_BYTES:]
        if stamped:
            ts = sample.timestamp
            if ts is None:
                return False
            try:
                if _zid_bytes(str(ts.get_id())) != zid:
                    return False
            except ValueError:
                return False
        want = _mac(self.token, zid, str(sample.key_expr), sample.payload.to_bytes())
        return hmac.compare_digest(mac, want)


@dataclass
class _Publisher:
    last_ns: int
    last_seq: int | None


@dataclass
class _Anchor:
    pubs: dict[bytes, _Publisher] = field(default_factory=dict)
    contested: bool = False
    detections: int = 0


class PublisherGuard:
    """Two publishers under one anchor key (see the module docstring); thread-safe.

    :meth:`check` is called for every anchor message with the nonce attached to it and its
    sequence number; it says whether to use the message and whether the anchor just became
    contested or trusted again.
    """

    def __init__(self, window_s: float = CONTEST_WINDOW_S) -> None:
        self.window_ns = round(window_s * 1e9)
        self.anchors: dict[str, _Anchor] = {}
        self._lock = threading.Lock()
        self._copies = 0

    def check(self, anchor_id: str, nonce: bytes | None, seq: int | None,
              now_ns: int) -> tuple[bool, str | None]:
        """``(use, event)``: ``use`` False while the anchor is contested; ``event``
        ``"contested"`` when it just became so, ``"trusted"`` when one publisher remains."""
        with self._lock:
            a = self.anchors.setdefault(anchor_id, _Anchor())
            ident = nonce if nonce is not None else b""
            pub = a.pubs.get(ident)
            if pub is not None and seq is not None and pub.last_seq is not None \
                    and seq <= pub.last_seq:
                # the same nonce but no new sequence number: a copy of another's messages
                self._copies += 1
                ident = b"copy:" + ident
                pub = a.pubs.get(ident)
            if pub is None:
                pub = a.pubs[ident] = _Publisher(now_ns, None)
            pub.last_ns = now_ns
            if seq is not None and not ident.startswith(b"copy:"):
                pub.last_seq = seq
            for other in [k for k, p in a.pubs.items() if now_ns - p.last_ns > self.window_ns]:
                del a.pubs[other]
            many = len(a.pubs) > 1
            event = None
            if many and not a.contested:
                a.contested, event = True, "contested"
                a.detections += 1
            elif not many and a.contested:
                a.contested, event = False, "trusted"
            return not a.contested, event

    def forget(self, anchor_id: str) -> None:
        """The anchor's liveliness token went away (its process ended): its publishers are
        forgotten, so a restarted anchor (a new nonce) is not taken for a second one."""
        with self._lock:
            a = self.anchors.get(anchor_id)
            if a is not None:
                a.pubs.clear()
                a.contested = False

    def contested(self) -> list[str]:
        with self._lock:
            return sorted(k for k, a in self.anchors.items() if a.contested)

    def detections(self) -> dict[str, int]:
        with self._lock:
            return {k: a.detections for k, a in self.anchors.items() if a.detections}

    def publishers(self, anchor_id: str) -> int:
        with self._lock:
            a = self.anchors.get(anchor_id)
            return len(a.pubs) if a is not None else 0
