"""Scoring of a live emulation against the true trajectories, and its summary table.

Every node-epoch counts: the run's node-epochs are every emulated node x every fusion epoch of
the run after the first ``skip_s`` (2 s: the anchors start and the trackers initialise); a
node-epoch without an estimate, or whose estimate has no position, is a miss (it counts
against availability and the floor accuracy over all node-epochs). The statistics are
:func:`diffpos.metrics.score` (the one scorer of emulate, replay and the benchmarks); this
module only collects the estimates (v1 or v2) as they arrive.
"""

from __future__ import annotations

import collections
import shutil
import textwrap
from typing import Any

import numpy as np

from diffpos.floor_calibration import probability_rows
from diffpos.metrics import percentiles, score
from diffpos_services.wire import messages as M

__all__ = ["SKIP_S", "SUMMARY_PERCENTILES", "Scorer", "format_responders", "format_summary",
           "summary_width"]

#: percentiles of the emulate summary
SUMMARY_PERCENTILES = (50, 67, 90, 95)
#: node-epochs of the first seconds are not scored
SKIP_S = 2.0


class Scorer:
    """The estimates of a run against the true node trajectories (emulation only).

    Parameters
    ----------
    nodes : list of (node_id, trajectory)
        Every emulated node (``trajectory.position_m(t_s)``).
    building : diffpos.scenario.Building
    t0_ns : int [ns]
        Start of the run (emulated time 0; on the fusion's epoch grid).
    period_ns : int [ns]
        Fusion epoch period.
    end_ns : int or None [ns]
        End of the run (its epochs up to it are expected); None: up to the newest estimate.
    skip_s : float [s]
        Node-epochs before ``t0 + skip_s`` are not scored.
    """

    def __init__(self, nodes: list[tuple[str, Any]], building, t0_ns: int, *,
                 period_ns: int = 100_000_000, end_ns: int | None = None,
                 skip_s: float = SKIP_S) -> None:
        self.traj = dict(nodes)
        self.building = building
        self.t0_ns = t0_ns
        self.period_ns = period_ns
        self.end_ns = end_ns
        self.e0 = t0_ns // period_ns
        self.k_skip = int(np.ceil(skip_s * 1e9 / period_ns - 1e-9))
        self.count = 0
        self.status: collections.Counter[str] = collections.Counter()
        self.methods: collections.Counter[str] = collections.Counter()
        self.epochs: dict[str, set[int]] = collections.defaultdict(set)
        # (node, epoch) -> (t_ns, position or None, covariance or None, floor or None, peb,
        #                   floor probabilities (() for v1 or without a position))
        self.rows: dict[tuple[str, int], tuple] = {}
        self.scored = 0  # estimates in the scored window
        self.scored_with_position = 0
        #: node -> its newest estimate: (epoch, t_ns, status)
        self.newest: dict[str, tuple[int, int, str]] = {}
        #: node -> its newest usable fix: (epoch, t_ns, floor or -1, probability of that
        #: floor (NaN: none published), 3D error [m] (NaN: unknown node), true floor or -1)
        self.last_fix: dict[str, tuple[int, int, int, float, float, int]] = {}

    def add(self, est: Any) -> float | None:
        """Count ``est`` (v1 or v2); its 3D error [m] if it has a usable position and a known
        node, else None."""
        self.count += 1
        self.status[est.status] += 1
        self.methods[getattr(est, "method", "dnls, lls or ippa (estimate v1)")] += 1
        self.epochs[est.node_id].add(est.epoch)
        tr = self.traj.get(est.node_id)
        usable = est.position_m is not None and est.status in M.GOOD_STATUSES
        if est.epoch - self.e0 >= self.k_skip and tr is not None:
            self.scored += 1
            self.scored_with_position += usable
        self.rows[(est.node_id, est.epoch)] = (
            est.t_ns, est.position_m if usable else None,
            est.covariance_m2 if usable else None, est.floor_index if usable else None,
            est.peb_m if usable else None,
            getattr(est, "floor_probabilities", ()) if usable else ())
        if est.node_id not in self.newest or self.newest[est.node_id][0] <= est.epoch:
            self.newest[est.node_id] = (est.epoch, est.t_ns, est.status)
        if not usable:
            return None
        err, true_floor = float("nan"), -1
        if tr is not None:
            truth = np.asarray(tr.position_m((est.t_ns - self.t0_ns) * 1e-9), float)
            err = float(np.linalg.norm(np.asarray(est.position_m) - truth))
            true_floor = int(self.building.floor_index(truth[2]))
        if est.node_id not in self.last_fix or self.last_fix[est.node_id][0] <= est.epoch:
            floor = -1 if est.floor_index is None else int(est.floor_index)
            probs = getattr(est, "floor_probabilities", ()) or ()
            p = float(probs[floor]) if 0 <= floor < len(probs) else float("nan")
            self.last_fix[est.node_id] = (est.epoch, est.t_ns, floor, p, err, true_floor)
        return None if tr is None else err

    def placed(self) -> dict[str, tuple[int, float, float]]:
        """Responders whose newest estimate has a usable position: node -> (floor, floor
        probability (NaN: none), 3D error [m] (NaN: unknown))."""
        out = {}
        for nid, (epoch, _t, _st) in self.newest.items():
            fix = self.last_fix.get(nid)
            if fix is not None and fix[0] == epoch:
                out[nid] = (fix[2], fix[3], fix[4])
        return out

    def responders(self) -> list[dict[str, Any]]:
        """Every emulated responder at the end: its newest status, the floor of its last
        usable fix and that floor's probability, the age of that fix (at the newest estimate
        of the run) [s], its 3D error [m] and the true floor then (None where unknown)."""
        ref = max((t for _, t, _ in self.newest.values()), default=None)
        rows = []
        for nid in sorted(set(self.traj) | set(self.newest)):
            new = self.newest.get(nid)
            fix = self.last_fix.get(nid)
            row: dict[str, Any] = {"node": nid, "status": new[2] if new else None,
                                   "floor": None, "probability": None, "age_s": None,
                                   "error_m": None, "true_floor": None}
            if fix is not None:
                _e, t, floor, p, err, true_floor = fix
                row.update(floor=floor if floor >= 0 else None,
                           probability=p if np.isfinite(p) else None,
                           age_s=(ref - t) * 1e-9 if ref is not None else None,
                           error_m=err if np.isfinite(err) else None,
                           true_floor=true_floor if true_floor >= 0 else None)
            rows.append(row)
        return rows

    def live_counts(self) -> tuple[int, int]:
        """Estimates so far in the scored window, and those with a position (the status line;
        the summary's availability divides the latter by every expected node-epoch)."""
        return self.scored, self.scored_with_position

    def _grid(self) -> list[tuple[str, int]]:
        """Every scored node-epoch ``(node, epoch)``."""
        if self.end_ns is not None:
            k_end = -(-(self.end_ns - self.t0_ns) // self.period_ns)
        else:
            k_end = max((e for _, e in self.rows), default=self.e0 - 1) - self.e0 + 1
        return [(nid, self.e0 + k) for nid in self.traj for k in range(self.k_skip, k_end)]

    def arrays(self) -> dict[str, np.ndarray]:
        """Estimate, truth, floors, covariance, PEB and floor probabilities (N, F; F = 0 when
        no estimate has any) of every scored node-epoch (NaN / -1 where there is none)."""
        grid = self._grid()
        n = len(grid)
        vectors = [()] * n
        est = np.full((n, 3), np.nan)
        cov = np.full((n, 3, 3), np.nan)
        truth = np.zeros((n, 3))
        e_floor = np.full(n, -1, np.int64)
        peb = np.full(n, np.nan)
        for i, (nid, ep) in enumerate(grid):
            row = self.rows.get((nid, ep))
            t_ns = row[0] if row is not None else ep * self.period_ns
            truth[i] = self.traj[nid].position_m((t_ns - self.t0_ns) * 1e-9)
            if row is None or row[1] is None:
                continue
            est[i] = row[1]
            if row[2] is not None:
                cov[i] = row[2]
            e_floor[i] = -1 if row[3] is None else row[3]
            peb[i] = np.nan if row[4] is None else row[4]
            vectors[i] = row[5]
        probs = probability_rows(vectors)
        probs = np.full((n, 0), np.nan) if probs is None else probs
        t_floor = np.asarray(self.building.floor_index(truth[:, 2]), np.int64)
        return {"estimate": est, "truth": truth, "estimate_floor": e_floor,
                "truth_floor": t_floor, "covariance": cov, "peb": peb, "floor_probabilities": probs,
                "missing": np.array([(g not in self.rows) for g in grid], bool)}

    def summary(self) -> dict[str, Any]:
        a = self.arrays()
        s = score(a["estimate"], a["truth"], estimate_floor=a["estimate_floor"],
                  truth_floor=a["truth_floor"], covariance_m2=a["covariance"],
                  floor_probabilities=a["floor_probabilities"] if a["floor_probabilities"].size
                  else None, q=SUMMARY_PERCENTILES)
        strip = lambda d: {k: v for k, v in d.items() if k.startswith("p")}  # noqa: E731
        peb = a["peb"][np.isfinite(a["peb"])]
        return {
            "estimates": self.count,
            "with_position": sum(r[1] is not None for r in self.rows.values()),
            "status": dict(self.status),
            "fusion_method": ", ".join(sorted(self.methods)) or None,
            "skip_s": self.k_skip * self.period_ns * 1e-9,
            "node_epochs": s.node_epochs,
            "node_epochs_without_estimate": int(a["missing"].sum()),
            "availability": s.availability,
            "error_3d_m": strip(s.error_3d_m),
            "error_z_m": strip(s.error_z_m),
            "peb_m": percentiles(peb, SUMMARY_PERCENTILES, max_mean=False),
            # over ALL scored node-epochs (a miss is a wrong floor); and over the fixes
            "floor_accuracy": s.floor_accuracy_all,
            "floor_accuracy_fixes": s.floor_accuracy_fixes,
            "ellipsoid_coverage_95": s.ellipsoid_coverage,
            # diffpos.floor_calibration (None: no floor probabilities, e.g. estimate v1)
            "floor_calibration": s.floor_calibration,
            "responders": self.responders(),
        }


def _pct(v: float | None) -> str:
    return "-" if v is None else f"{100 * v:.1f} %"


def _model(s: dict[str, Any]) -> str:
    """The fusion's method (from its estimates) and, for D-NLS, the orchestrator's edge."""
    method = s.get("fusion_method")
    if method and method.startswith("mnls"):
        return (f"{method}: the first-arrival path model of the scenario's building (every "
                "mechanism, per floor)")
    return s.get("model", "-") if not method else f"{method}; {s.get('model', '-')}"


def summary_width() -> int:
    """Width of the summary: the terminal's (80 when not a terminal), kept within 60..100."""
    return min(max(shutil.get_terminal_size((80, 24)).columns, 60), 100)


def _wrap_rows(rows: list[tuple[str, str]], width: int) -> str:
    """``name  value`` rows, values wrapped under themselves so no line exceeds ``width``."""
    w = max(len(r[0]) for r in rows)
    out = []
    for k, v in rows:
        lines = textwrap.wrap(v, max(width - w - 2, 20), break_long_words=True,
                              break_on_hyphens=False) or [""]
        out.append(f"{k:<{w}}  {lines[0]}")
        out += [f"{'':<{w}}  {line}" for line in lines[1:]]
    return "\n".join(out)


#: ``rejected`` reasons that count node-epochs the live overload policy did not solve
#: (``fusion.overload``), not ranges
_NODE_EPOCH_REASONS = ("superseded", "overloaded")

def _gating_rows(s: dict[str, Any], f) -> list[tuple[str, str]]:
    """The fusion's counters, worded so they cannot be mistaken for the status counts: a fix
    that failed the consistency test is a GATING_FAILED estimate (the ``status`` row); the
    fusion's ``gated`` counter counts single measurements excluded from fixes."""
    fu = s.get("fusion")
    if not fu:
        return []
    lat = fu["latency_ms"]
    failed = s.get("status", {}).get("GATING_FAILED", 0)
    rej = fu["rejected"] or 0
    behind = ""
    if isinstance(rej, dict):  # per reason; the overload policy's counts are node-epochs
        shed = {k: rej[k] for k in _NODE_EPOCH_REASONS if rej.get(k)}
        rej = ", ".join(f"{k} {v}" for k, v in sorted(rej.items())
                        if k not in _NODE_EPOCH_REASONS) or "0"
        if shed:
            behind = ("; node-epochs not solved (the fusion was behind its input): "
                      + ", ".join(f"{k} {v}" for k, v in shed.items()))
    return [
        ("gating", f"{failed} estimates GATING_FAILED (whole fix rejected); "
                   f"{fu['gated']} single measurements excluded from fixes; ranges "
                   f"rejected: {rej}; late ranges {fu['late_ranges']}{behind}"),
        ("fusion latency", f"p50 {f(lat['p50'], ' ms')}  p99 {f(lat['p99'], ' ms')}"),
    ]


def _calibration_row(s: dict[str, Any]) -> str:
    """How far the published floor's probability can be trusted (diffpos.floor_calibration)."""
    c = s.get("floor_calibration")
    if c is None:
        return "none reported (estimate v1 or a method without them): calibration not measured"
    hi = c["reliability"][-1]
    right = "-" if hi["fraction_right"] is None else _pct(hi["fraction_right"])
    return (f"confidently wrong (wrong floor at p >= {c['confident']:g}) "
            f"{c['confidently_wrong_count']} = {100 * c['confidently_wrong']:.2f} % of all "
            f"node-epochs; published at p >= {hi['bin'][0]:g}: {hi['count']}, {right} right; "
            f"ECE {c['ece']:.3f}, log score {c['log_score']:.3f} nats")


def _pace(speed: float | None) -> str:
    """How emulated time ran: ``lockstep`` (speed 0: as fast as the fusion) or ``at x2``."""
    if speed is None:
        return ""
    return "in lockstep (as fast as the fusion)" if speed == 0 else f"at x{speed:g}"


def format_responders(rows: list[dict[str, Any]], width: int = 100) -> str:
    """The end-of-run table: one line per responder (id, newest status, floor of the last
    fix and its probability, age of that fix, its 3D error, the true floor then, marked
    when wrong); two tables side by side when ``width`` holds them."""
    if not rows:
        return ""
    w_id = max(4, *(len(r["node"]) for r in rows))
    w_st = max(6, *(len(r["status"] or "-") for r in rows))

    def cell(r: dict[str, Any]) -> str:
        fl = "-" if r["floor"] is None else f"F{r['floor']}"
        p = "-" if r["probability"] is None else f"{100 * r['probability']:.0f}%"
        age = "-" if r["age_s"] is None else f"{r['age_s']:.1f}s"
        err = "-" if r["error_m"] is None else f"{r['error_m']:.2f}"
        tf = r["true_floor"]
        true = "" if tf is None else ("" if r["floor"] == tf else f"F{tf}!")
        return (f"{r['node']:<{w_id}} {r['status'] or '-':<{w_st}} {fl:>3} {p:>4} {age:>5} "
                f"{err:>5} {true:<3}")

    head = (f"{'node':<{w_id}} {'status':<{w_st}} {'flr':>3} {'p':>4} {'age':>5} "
            f"{'err':>5} {'tru':<3}")
    cells = [cell(r) for r in rows]
    n_cols = 2 if 2 * len(head) + 3 <= width and len(rows) > 12 else 1
    per = -(-len(cells) // n_cols)
    lines = [" | ".join([head] * n_cols).rstrip()]
    for i in range(per):
        lines.append(" | ".join(cells[i + c * per] for c in range(n_cols)
                                if i + c * per < len(cells)).rstrip())
    return "\n".join(lines)


def format_summary(s: dict[str, Any], *, width: int | None = None) -> str:
    """The summary as a plain-text table that fits ``width`` columns (default
    :func:`summary_width`): values wrap under themselves. An optional ``notes`` entry (list
    of str) is printed last, one wrapped paragraph per note."""
    def f(v: float | None, unit: str = " m") -> str:
        return "-" if v is None else f"{v:.3f}{unit}"

    width = summary_width() if width is None else width
    rows = [
        ("run", f"{s.get('run_id', '-')}  ({s.get('anchors')} anchors x {s.get('nodes')} nodes, "
                f"{s.get('duration_s')} s {_pace(s.get('speed'))}, channel {s.get('channel')})"),
        ("model", _model(s)),
        ("estimates", f"{s.get('estimates', 0)} ({s.get('with_position', 0)} with a position)"),
        ("status", ", ".join(f"{k} {v}" for k, v in sorted(s.get("status", {}).items())) or "-"),
        ("node-epochs", f"{s.get('node_epochs', 0)} after the first {s.get('skip_s', 0):g} s "
                        f"({s.get('node_epochs_without_estimate', 0)} without an estimate)"),
        ("availability", f"{_pct(s.get('availability'))} of the node-epochs have a position"),
        ("floor accuracy", f"{_pct(s.get('floor_accuracy'))} of all node-epochs "
                           f"({_pct(s.get('floor_accuracy_fixes'))} of the fixes)"),
    ]
    for name, key in (("3D error", "error_3d_m"), ("z error", "error_z_m"), ("PEB", "peb_m")):
        p = s.get(key, {})
        rows.append((name, "  ".join(f"p{q} {f(p.get(f'p{q}'))}" for q in SUMMARY_PERCENTILES)))
    rows.append(("95 % ellipsoid", f"{_pct(s.get('ellipsoid_coverage_95'))} of the fixes hold "
                                   "the truth"))
    rows.append(("floor calib.", _calibration_row(s)))
    rows += _gating_rows(s, f)
    if s.get("lost"):
        rows.append(("lost", ", ".join(s["lost"])))
    if s.get("recording"):
        rows.append(("recording", f"{s['recording']}  (diffpos replay / inspect / to-rerun FILE)"))
    # the recording row names the one-part recording: its note would say it a second time
    notes = [n for n in s.get("notes") or () if not s.get("recording")
             or str(n) != f"recording: {s['recording']}"]
    for i, note in enumerate(notes):
        rows.append(("notes" if i == 0 else "", str(note)))
    table = format_responders(s.get("responders") or [], width)
    if not table:
        return _wrap_rows(rows, width)
    legend = ("responders at the end (flr, p: floor of the last fix and its probability; age: "
              "of that fix; err: its 3D error [m]; tru: the true floor when it differs, !)")
    return "\n".join([_wrap_rows(rows, width), *textwrap.wrap(legend, width), table])
