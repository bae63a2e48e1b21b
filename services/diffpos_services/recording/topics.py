"""What an MCAP topic (a bus key expression, or a recording-only topic) means.

* :func:`parse_topic` - kind and ids of a topic (:mod:`diffpos_services.wire.keys` spells and
  parses every key; this adds the plain-dict form the recording code uses).
* :class:`SeqTracker` - gaps and repeats in the publishers' sequence numbers.
* :func:`natural_key` - ``n2`` before ``n10`` (report and listing order).
"""

from __future__ import annotations

import functools
import re

from diffpos_services.wire.keys import PREFIX, SEQUENCE_STREAMS, parse_recording_topic

__all__ = ["SEQUENCED_KINDS", "SeqTracker", "natural_key", "parse_topic"]


def parse_topic(topic: str) -> tuple[str, dict[str, str]]:
    """Classify a key expression / MCAP topic.

    Parameters
    ----------
    topic : str
        e.g. ``diffpos/site1/anchor/a3/range/n12``.

    Returns
    -------
    kind : str
        A :func:`diffpos_services.wire.keys.parse_key` kind (``anchor_state``, ``range``,
        ``estimate``, ``diagnostics``, ``truth_node``, ``truth_anchor``, ``run_control``, ...),
        or one of the recording-only kinds ``liveliness`` (the recorder's event channel) and
        ``replay_estimate`` (estimates written by ``diffpos replay``), or ``unknown``.
    fields : dict
        ``site`` and, when present, ``anchor`` and ``node``.
    """
    pk = parse_recording_topic(topic)
    if pk is None:
        return "unknown", {}
    fields = {"site": pk.site}
    if pk.anchor_id is not None:
        fields["anchor"] = pk.anchor_id
    if pk.node_id is not None:
        fields["node"] = pk.node_id
    return pk.kind, fields


#: kinds whose messages carry a ``seq`` field (the others - truth, diagnostics, run control,
#: liveliness events, foreign channels - are not checked for gaps)
SEQUENCED_KINDS = frozenset(SEQUENCE_STREAMS)


class SeqTracker:
    """Gaps and repeats in publisher sequence numbers, per sequence stream.

    A stream is one publisher's counter (:data:`SEQUENCE_STREAMS`: one per anchor, one for
    the fusion's estimates). Only :data:`SEQUENCED_KINDS` are tracked.

    Attributes
    ----------
    gaps : dict[str, int]
        Stream -> messages missing (sum of the holes).
    out_of_order : dict[str, int]
        Stream -> sequence numbers that went backwards or repeated.
    gap_list : list of (stream, first_missing, last_missing)
        The holes, first 1000.
    """

    def __init__(self) -> None:
        self._stream: dict[str, str | None] = {}
        self._last: dict[str, int] = {}
        self.gaps: dict[str, int] = {}
        self.out_of_order: dict[str, int] = {}
        self.gap_list: list[tuple[str, int, int]] = []
        self.total_gaps = 0
        self.total_out_of_order = 0

    def stream_of(self, topic: str) -> str | None:
        """Sequence stream of a topic (``None``: not tracked)."""
        st = self._stream.get(topic, "")
        if st == "":
            kind, fields = parse_topic(topic)
            if kind not in SEQUENCED_KINDS:
                st = None
            else:
                st = f"{PREFIX}/{fields['site']}/" + SEQUENCE_STREAMS[kind].format(**fields)
            self._stream[topic] = st
        return st

    def add(self, topic: str, seq: int) -> int:
        """Account one message; returns the number of messages found missing before it."""
        st = self.stream_of(topic)
        if st is None:
            return 0
        return self.add_stream(st, seq)

    def add_stream(self, st: str, seq: int) -> int:
        """:meth:`add` with the topic's stream already known (:meth:`stream_of`)."""
        last = self._last.get(st)
        self._last[st] = seq
        if last is None:
            return 0
        if seq > last + 1:
            n = seq - last - 1
            self.gaps[st] = self.gaps.get(st, 0) + n
            self.total_gaps += n
            if len(self.gap_list) < 1000:
                self.gap_list.append((st, last + 1, seq - 1))
            return n
        if seq <= last:
            self.out_of_order[st] = self.out_of_order.get(st, 0) + 1
            self.total_out_of_order += 1
        return 0


# ----------------------------------------------------------------------------------------
# schemas
# ----------------------------------------------------------------------------------------


@functools.lru_cache(maxsize=1 << 16)
def natural_key(s: str) -> tuple:
    """Natural sort key (``n2`` < ``n10``); cached: replay sorts by node id per estimate."""
    return tuple(int(t) if t.isdigit() else t for t in re.split(r"(\d+)", s))
