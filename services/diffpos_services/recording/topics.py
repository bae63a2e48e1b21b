"""What an MCAP topic (a bus key expression, or a recording-only topic) means.

* :func:`parse_topic` - kind and ids of a topic (:mod:`diffpos_services.wire.keys` spells and
  parses every key; this adds the plain-dict form the recording code uses).
* :class:`SeqTracker` - gaps and repeats in the publishers' sequence numbers.
* :func:`natural_key` - ``n2`` before ``n10`` (report and listing order).
"""

from __future__ import annotations

import functools
import re

from diffpos_services.fusion.config import shard_of
from diffpos_services.wire.keys import PREFIX, SEQUENCE_STREAMS, parse_recording_topic

__all__ = ["LOCK_AFTER", "MAX_INFERRED_SHARDS", "SEQUENCED_KINDS", "SeqTracker", "natural_key",
           "parse_topic"]


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


#: Most fusion shards :class:`SeqTracker` tells apart in the estimates' sequence numbers.
MAX_INFERRED_SHARDS = 8
#: Estimates of a site after which the shard count found is kept (the other candidates are
#: no longer followed: a wrong one has an anomaly at about every change of publisher).
LOCK_AFTER = 1000


class _EstimateStreams:
    """The estimates of one site: each fusion shard numbers its own (``diffpos fusion
    --shard K/N``: one counter per process over its responders, the nodes whose
    :func:`~diffpos_services.fusion.config.shard_of` is K), all on ``node/*/estimate``. An
    estimate does not say which shard published it and the tracker does not know N, so every
    candidate N in ``1 .. MAX_INFERRED_SHARDS`` keeps its own per-shard counters and holes;
    the one with the fewest anomalies (holes + repeats; ties: the fewer shards) is reported.
    The true N has none without loss; another N splits or merges counters and has many.
    After :data:`LOCK_AFTER` estimates the best is kept and only it is followed (cheap).
    With ``shards`` (the count the run configuration records, e.g. in a replay) only that N
    is followed from the first estimate: nothing is inferred."""

    def __init__(self, site: str, shards: int | None = None) -> None:
        self.base = f"{PREFIX}/{site}/" + SEQUENCE_STREAMS["estimate"]
        n_cands = range(1, max(MAX_INFERRED_SHARDS, shards or 1) + 1)
        self.last: list[dict[int, int]] = [{} for _ in n_cands]
        self.gaps: list[dict[int, int]] = [{} for _ in n_cands]
        self.repeats: list[dict[int, int]] = [{} for _ in n_cands]
        self.holes: list[list[tuple[int, int, int]]] = [[] for _ in n_cands]
        self.bad = [0 for _ in n_cands]  # holes + repeats per candidate
        self.n_gaps = [0 for _ in n_cands]  # messages missing per candidate
        self.n_repeats = [0 for _ in n_cands]
        self._best = 0
        self.seen = 0  # estimates while undecided
        self._locked: int | None = None  # the candidate kept after LOCK_AFTER estimates
        if shards is not None:  # recorded: followed alone from the start
            self._best = self._locked = shards - 1

    def best(self) -> int:
        """Index of the candidate shard count reported (``N - 1``)."""
        return self._best

    def add(self, shard_by_n: tuple[int, ...], seq: int) -> int:
        """One estimate of the node whose shard is ``shard_by_n[N - 1]`` for N shards;
        returns the messages found missing before it by the reported candidate."""
        if self._locked is not None:
            return self._one(self._locked, shard_by_n[self._locked], seq)
        missing = [self._one(i, k, seq) for i, k in enumerate(shard_by_n)]
        self.seen += 1
        if self.seen >= LOCK_AFTER:  # decided: only the reported candidate from now on
            self._locked = self._best
        return missing[self._best]

    def _one(self, i: int, k: int, seq: int) -> int:
        """Candidate ``i``'s shard ``k`` numbered ``seq``: the messages missing before it."""
        last = self.last[i].get(k)
        self.last[i][k] = seq
        if last is None or seq == last + 1:
            return 0
        self.bad[i] += 1
        if seq > last + 1:
            n = seq - last - 1
            self.gaps[i][k] = self.gaps[i].get(k, 0) + n
            self.n_gaps[i] += n
            if len(self.holes[i]) < 1000:
                self.holes[i].append((k, last + 1, seq - 1))
        else:
            n = 0
            self.repeats[i][k] = self.repeats[i].get(k, 0) + 1
            self.n_repeats[i] += 1
        if self._locked is None:
            self._best = min(range(len(self.bad)), key=lambda j: (self.bad[j], j))
        return n

    def name(self, i: int, k: int) -> str:
        """The stream's name: ``.../node/*/estimate`` (one fusion) or ``... shard K/N``."""
        return self.base if i == 0 else f"{self.base} shard {k}/{i + 1}"

    def reported(self) -> tuple[dict[str, int], dict[str, int], list[tuple[str, int, int]]]:
        """``(gaps, repeats, holes)`` of the reported candidate, by stream name."""
        i = self.best()
        return ({self.name(i, k): n for k, n in self.gaps[i].items()},
                {self.name(i, k): n for k, n in self.repeats[i].items()},
                [(self.name(i, k), a, b) for k, a, b in self.holes[i]])


def _shards_of(node: str, shards: int | None) -> tuple[int, ...]:
    """The shard owning ``node`` for every candidate shard count ``1 .. MAX_INFERRED_SHARDS``
    (with a known count ``shards``: only that one's entry is filled, the others 0)."""
    if shards is not None:
        return (0,) * (shards - 1) + (shard_of(node, shards),)
    return tuple(shard_of(node, n) for n in range(1, MAX_INFERRED_SHARDS + 1))


class SeqTracker:
    """Gaps and repeats in publisher sequence numbers, per sequence stream.

    A stream is one publisher's counter (:data:`SEQUENCE_STREAMS`: one per anchor, one for
    the fusion's estimates: one per fusion shard when several share the responders, told
    apart by the node ids as :class:`_EstimateStreams` says). Only :data:`SEQUENCED_KINDS`
    are tracked.

    Parameters
    ----------
    estimate_shards : int, optional
        The fusion shards of the run as its run configuration records them (a replay, which
        has read it): the estimates' streams are those of that count, not inferred from the
        sequence numbers (``None``: inferred, the recorder's and live use).

    Attributes
    ----------
    gaps : dict[str, int]
        Stream -> messages missing (sum of the holes).
    out_of_order : dict[str, int]
        Stream -> sequence numbers that went backwards or repeated.
    gap_list : list of (stream, first_missing, last_missing)
        The holes, first 1000 (the estimates' after the others').
    total_gaps, total_out_of_order : int
        Their sums.
    """

    def __init__(self, estimate_shards: int | None = None) -> None:
        if estimate_shards is not None and estimate_shards < 1:
            raise ValueError(f"estimate_shards={estimate_shards}: must be >= 1")
        self._shards = estimate_shards
        self._stream: dict[str, str | None] = {}
        self._last: dict[str, int] = {}
        self._gaps: dict[str, int] = {}
        self._out_of_order: dict[str, int] = {}
        self._gap_list: list[tuple[str, int, int]] = []
        self._total_gaps = self._total_ooo = 0
        #: estimate stream token (:meth:`stream_of`) -> (the site's streams, node's shards)
        self._est_topic: dict[str, tuple[_EstimateStreams, tuple[int, ...]]] = {}
        self._est_site: dict[str, _EstimateStreams] = {}

    def stream_of(self, topic: str) -> str | None:
        """Sequence stream of a topic (``None``: not tracked; for an estimate, a token that
        :meth:`add_stream` resolves to its fusion shard's stream)."""
        st = self._stream.get(topic, "")
        if st == "":
            kind, fields = parse_topic(topic)
            if kind not in SEQUENCED_KINDS:
                st = None
            elif kind == "estimate":
                st = f"{PREFIX}/{fields['site']}/node/{fields['node']}/estimate"
                site = self._est_site.get(fields["site"])
                if site is None:
                    site = self._est_site[fields["site"]] = _EstimateStreams(
                        fields["site"], self._shards)
                self._est_topic[st] = (site, _shards_of(fields["node"], self._shards))
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
        est = self._est_topic.get(st)
        if est is not None:
            return est[0].add(est[1], seq)
        last = self._last.get(st)
        self._last[st] = seq
        if last is None:
            return 0
        if seq > last + 1:
            n = seq - last - 1
            self._gaps[st] = self._gaps.get(st, 0) + n
            self._total_gaps += n
            if len(self._gap_list) < 1000:
                self._gap_list.append((st, last + 1, seq - 1))
            return n
        if seq <= last:
            self._out_of_order[st] = self._out_of_order.get(st, 0) + 1
            self._total_ooo += 1
        return 0

    def _reported(self) -> list[tuple[dict[str, int], dict[str, int], list]]:
        return [s.reported() for s in self._est_site.values()]

    @property
    def gaps(self) -> dict[str, int]:
        out = dict(self._gaps)
        for g, _, _ in self._reported():
            out.update(g)
        return out

    @property
    def out_of_order(self) -> dict[str, int]:
        out = dict(self._out_of_order)
        for _, r, _ in self._reported():
            out.update(r)
        return out

    @property
    def gap_list(self) -> list[tuple[str, int, int]]:
        out = list(self._gap_list)
        for _, _, h in self._reported():
            out += h
        return out[:1000]

    @property
    def total_gaps(self) -> int:
        return self._total_gaps + sum(s.n_gaps[s.best()] for s in self._est_site.values())

    @property
    def total_out_of_order(self) -> int:
        return self._total_ooo + sum(s.n_repeats[s.best()] for s in self._est_site.values())


# ----------------------------------------------------------------------------------------
# schemas
# ----------------------------------------------------------------------------------------


@functools.lru_cache(maxsize=1 << 16)
def natural_key(s: str) -> tuple:
    """Natural sort key (``n2`` < ``n10``); cached: replay sorts by node id per estimate."""
    return tuple(int(t) if t.isdigit() else t for t in re.split(r"(\d+)", s))
