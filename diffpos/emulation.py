"""The anchor measurement model of the emulation: nodes, time base, navigation, clock, ranges.

What an emulated UAV anchor measures and reports, as pure functions of the scenario, the
time and random generators passed in (``numpy.random.Generator``; never global):

- :func:`emulation_nodes`: the nodes every process of a run emulates (the scenario's nodes,
  or :func:`responders` walking between floors);
- :class:`TimeBase`: emulated time ``t = t0_ns + speed * (wall - wall_t0_ns)``; trajectories
  are evaluated at ``(t - t0_ns) / 1e9`` seconds since the start of the run;
- :class:`NavigationError`: the anchor's own GNSS/barometer error (a slowly varying
  Gauss-Markov bias plus white noise) and velocity noise;
- :func:`clock_time_ns`: a true time stamped with the anchor's clock (offset + jitter);
- :func:`first_arrivals`: range, sigma, SNR and detection of the first-arriving path to each
  node (the O2I channel emulator of :mod:`diffpos.channel.emulator`, the ideal upper-edge path with
  noise at the ranging CRLB, or paths ray traced before the run: :mod:`diffpos.channel.traced`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np

from diffpos.channel.emulator import emulate_channel, first_arrival, pair_first_arrival
from diffpos.channel.linkbudget import db_to_linear, ranging_crlb_m
from diffpos.channel.traced import TracedLinks, traced_first_arrivals
from diffpos.geometry import window_edge_path
from diffpos.scenario import Scenario
from diffpos.trajectory import trajectory_from_dict

__all__ = [
    "NavigationError",
    "TimeBase",
    "clock_time_ns",
    "emulation_nodes",
    "first_arrivals",
    "responders",
    "warm_up_channel",
]


# ----------------------------------------------------------------------------- nodes
def responders(building, *, count: int = 6, seed: int = 0,
               speed_m_s: float = 1.2) -> list[tuple[str, Any]]:
    """A handful of responders walking inside ``building`` and taking the stairs.

    Responder ``i`` starts on floor ``i mod n_floors``, walks along the facade at a fixed depth,
    climbs (or descends) one floor on a 6 m stair run near a side wall and walks back, in a
    loop, at ``speed_m_s`` (in a one-floor building that leg stays on the level); the loop
    closes from the end of the walk back to its start, 2 m nearer the facade and one floor
    down (or up). On the level parts it is at the window's mid-height (the paper's
    Assumption 1); on the stairs it is not (a realistic model mismatch). Ids ``r01``...
    The whole loop stays inside the floors of any building wider than 11 m and deeper than 4 m
    (else ``ValueError``); the layout of buildings at least 20 m wide and 13 m deep is the
    one it always was.
    """
    rng = np.random.default_rng(seed)
    b = building
    x_lo, x_hi = b.edge_x_m
    if b.width_m <= 11.0 or b.depth_m <= 4.0:
        raise ValueError(f"responders need a building wider than 11 m (a 6 m stair run 4 m "
                         f"from the side wall) and deeper than 4 m, got {b.width_m:g} x "
                         f"{b.depth_m:g} m")
    h = b.nominal_node_height_m
    # the walk is at depth y and, after the stairs, y + 2 m: both at least 1 m from the back
    # wall; it starts between 8 m from the west wall and 12 m from the east one (the stairs
    # end 10 m from it), nearer the west wall in buildings narrower than 20 m
    y_hi = min(b.depth_m - 3.0, 10.0)
    y_lo = min(1.5, 0.5 * y_hi)
    xa_lo, xa_hi = x_lo + 8.0, x_hi - 12.0
    if xa_hi < xa_lo:
        xa_lo, xa_hi = x_lo + 0.5, max(x_hi - 12.0, x_lo + 0.5)
    out = []
    for i in range(count):
        f0 = i % b.n_floors
        # the next floor up (from the top floor: down); one floor: the stair leg stays level
        f1 = f0 + 1 if f0 + 1 < b.n_floors else max(f0 - 1, 0)
        z0 = float(b.floor_z_m(f0)) + h
        z1 = float(b.floor_z_m(f1)) + h
        y = float(rng.uniform(y_lo, y_hi))
        xa = float(rng.uniform(xa_lo, xa_hi))
        xs = x_hi - 4.0  # stairs start
        pts = [[xa, y, z0], [xs, y, z0], [xs, y + 2.0, z0], [xs - 6.0, y + 2.0, z1],
               [xa, y + 2.0, z1]]
        traj = trajectory_from_dict({"kind": "waypoints", "points_m": pts,
                                     "speed_m_s": speed_m_s, "loop": True})
        out.append((f"r{i + 1:02d}", traj))
    return out


def emulation_nodes(scenario: Scenario, *, max_nodes: int = 0) -> list[tuple[str, Any]]:
    """``[(node_id, trajectory)]`` to emulate (a function of the scenario only, so every
    process of a run agrees on it).

    The scenario's explicit nodes; if it only has a study grid (the paper's scenario), six
    :func:`responders` (layout seed 0) moving between floors. ``max_nodes > 0`` caps the list.
    """
    nodes = [(n.id, n.trajectory) for n in scenario.nodes]
    if not nodes:
        nodes = responders(scenario.building, count=6, seed=0)
    if max_nodes > 0:
        nodes = nodes[:max_nodes]
    return nodes


# ----------------------------------------------------------------------------- time base
@dataclass(frozen=True)
class TimeBase:
    """Mapping between wall clock and emulated time.

    Attributes
    ----------
    t0_ns : int [ns]
        Emulated time at the start of the run (trajectories' ``t_s = 0``).
    wall_t0_ns : int [ns]
        Wall clock (``time.time_ns()``) at which emulated time is ``t0_ns``.
    speed : float [-]
        Emulated seconds per wall second.
    duration_ns : int [ns]
        Run length in emulated time, 0 = unlimited.
    """

    t0_ns: int
    wall_t0_ns: int
    speed: float = 1.0
    duration_ns: int = 0

    def wall_of(self, t_ns: int) -> int:
        """Wall time [ns] at which emulated time is ``t_ns``."""
        return self.wall_t0_ns + round((t_ns - self.t0_ns) / self.speed)

    def now_ns(self, wall_ns: int) -> int:
        """Emulated time [ns] at wall time ``wall_ns``."""
        return self.t0_ns + round((wall_ns - self.wall_t0_ns) * self.speed)

    def t_s(self, t_ns: int | np.ndarray) -> Any:
        """Seconds since the start of the run (the trajectories' time) of ``t_ns``."""
        return (np.asarray(t_ns) - self.t0_ns) * 1e-9

    @classmethod
    def from_control(cls, rc: Any) -> TimeBase:
        """From a run-control message (``t0_ns``, ``wall_t0_ns``, ``speed``, ``duration_ns``)."""
        return cls(rc.t0_ns, rc.wall_t0_ns, rc.speed, rc.duration_ns)

    @classmethod
    def free_running(cls, wall_ns: int) -> TimeBase:
        """Real time, origin at the start of the UTC hour of ``wall_ns`` (shared by every
        process started within the hour without any coordination)."""
        hour = 3600 * 10**9
        t0 = wall_ns - wall_ns % hour
        return cls(t0, t0, 1.0, 0)


# ----------------------------------------------------------------------------- navigation
class NavigationError:
    """The anchor's navigation error: what it reports minus where it is.

    Position: a Gauss-Markov bias (time constant ``tau_s``, a fraction ``bias_fraction`` of
    the variance) plus white noise (the rest), per axis with sigmas ``(sigma_h_m, sigma_h_m,
    sigma_v_m)``; velocity: white noise of ``velocity_sigma_m_s``. Both draw from ``rng`` in
    call order (the initial bias at construction).
    """

    def __init__(self, *, sigma_h_m: float, sigma_v_m: float, bias_fraction: float,
                 tau_s: float, velocity_sigma_m_s: float, rng: np.random.Generator) -> None:
        self.rng = rng
        self.sigma_m = np.array([sigma_h_m, sigma_h_m, sigma_v_m])
        self.bias_fraction = bias_fraction
        self.tau_s = tau_s
        self.velocity_sigma_m_s = velocity_sigma_m_s
        self.bias = rng.normal(0, 1, 3) * self.sigma_m * np.sqrt(bias_fraction)
        self.last_t_s: float | None = None

    def position(self, t_s: float) -> np.ndarray:
        """Position error [m], shape (3,), at ``t_s`` [s] (non-decreasing between calls)."""
        fb = self.bias_fraction
        if self.last_t_s is not None:
            a = np.exp(-max(t_s - self.last_t_s, 0.0) / self.tau_s)
            self.bias = a * self.bias + np.sqrt(1 - a * a) * np.sqrt(
                fb
            ) * self.sigma_m * self.rng.normal(0, 1, 3)
        self.last_t_s = t_s
        white = self.rng.normal(0, 1, 3) * self.sigma_m * np.sqrt(1 - fb)
        return self.bias + white

    def velocity(self) -> np.ndarray:
        """Velocity error [m/s], shape (3,)."""
        return self.rng.normal(0, self.velocity_sigma_m_s, 3)


def clock_time_ns(t_true_ns: int, *, offset_ns: int, jitter_ns: int,
                  rng: np.random.Generator) -> int:
    """``t_true_ns`` read on the anchor's clock: constant offset plus Gaussian jitter [ns]
    (no draw when ``jitter_ns`` is 0)."""
    jitter = int(rng.normal(0, jitter_ns)) if jitter_ns else 0
    return int(t_true_ns + offset_ns + jitter)


# ----------------------------------------------------------------------------- ranges
def first_arrivals(anchor_m: np.ndarray, nodes_m: np.ndarray, scenario: Scenario, *,
                   channel: str = "emulator", ideal_snr_db: float = 20.0,
                   rng: np.random.Generator | None, kernel: bool = True,
                   traced: TracedLinks | None = None, t_s: np.ndarray | None = None
                   ) -> tuple[np.ndarray, ...]:
    """First-arriving path from one anchor to every node at ``B`` epochs.

    Parameters
    ----------
    anchor_m : ndarray, shape (B, 3) [m]
        The anchor's true position at each epoch.
    nodes_m : ndarray, shape (B, N, 3) [m]
        The nodes' true positions at each epoch.
    scenario : Scenario
        Building and radio.
    channel : {"emulator", "ideal", "raytrace"}
        ``emulator``: the O2I multipath emulator and first-arrival detection; ``ideal``: the
        upper-edge diffracted path with noise at the ranging CRLB of ``ideal_snr_db``;
        ``raytrace``: the paths of ``traced`` at times ``t_s`` with the emulator's detector
        and noise (:func:`diffpos.channel.traced.traced_first_arrivals`).
    rng : numpy.random.Generator
        Measurement noise.
    kernel : bool
        ``emulator``: the compiled per-pair detector (:func:`diffpos.channel.emulator.
        pair_first_arrival`, ~100x less CPU per epoch; the same draws, equal to rounding);
        ``False``: the numpy emulator (:func:`~diffpos.channel.emulator.emulate_channel` +
        :func:`~diffpos.channel.emulator.first_arrival`), the reference.
    traced : TracedLinks, optional
        ``raytrace``: this anchor's traced paths to the same N nodes.
    t_s : ndarray, shape (B,) [s], optional
        ``raytrace``: the epochs' times since the start of the run.

    Returns
    -------
    range_m, sigma_m, snr_db : ndarray, shape (B, N)
    detected : ndarray of bool, shape (B, N)
    """
    b, n = nodes_m.shape[:2]
    if channel == "raytrace":
        if traced is None or t_s is None:
            raise ValueError("channel 'raytrace' needs the traced paths (traced) and the "
                             "epochs' times (t_s)")
        fa = traced_first_arrivals(traced, t_s, anchor_m, nodes_m, radio=scenario.radio,
                                   rng=rng)
        return fa.range_m, fa.sigma_m, fa.snr_db, fa.detected
    if channel == "ideal":
        w = scenario.building.window_height_m
        path = window_edge_path(
            anchor_m[:, None, :],
            nodes_m,
            window_height_m=w,
            edge_x_m=scenario.building.edge_x_m,
        ).length_m
        snr = np.full((b, n), ideal_snr_db)
        sg = ranging_crlb_m(db_to_linear(snr), scenario.radio.bandwidth_hz)
        r = path + sg * rng.standard_normal((b, n))
        return r, sg, snr, np.ones((b, n), bool)
    if kernel:
        r, sg, snr, _, det = pair_first_arrival(
            np.repeat(np.asarray(anchor_m, dtype=np.float64), n, axis=0),
            nodes_m.reshape(b * n, 3), building=scenario.building, radio=scenario.radio,
            rng=rng)
        return r.reshape(b, n), sg.reshape(b, n), snr.reshape(b, n), det.reshape(b, n)
    ch = emulate_channel(
        anchor_m,
        nodes_m.reshape(b * n, 3),
        building=scenario.building,
        radio=scenario.radio,
    )
    if b > 1:  # keep the (epoch e, node i) x anchor-at-epoch-e pairs only
        rows = np.arange(b * n)
        cols = np.repeat(np.arange(b), n)
        fields = {}
        for f in dataclasses.fields(ch):
            v = getattr(ch, f.name)
            if isinstance(v, np.ndarray) and v.ndim == 3 and v.shape[:2] == (b * n, b):
                fields[f.name] = v[rows, cols][:, None, :]
        fields["anchors_m"] = anchor_m[:1]
        ch = dataclasses.replace(ch, **fields)
    fa = first_arrival(ch, radio=scenario.radio, rng=rng)
    r = fa.range_m[:, 0].reshape(b, n)
    sg = fa.sigma_m[:, 0].reshape(b, n)
    snr = fa.snr_db[:, 0].reshape(b, n)
    det = fa.detected[:, 0].reshape(b, n)
    return r, sg, snr, det


def warm_up_channel(anchor_m: np.ndarray, node_m: np.ndarray, scenario: Scenario, *,
                    channel: str = "emulator") -> None:
    """Exercise the channel code once without random draws (first-call costs paid before a
    real epoch). ``anchor_m``, ``node_m``: shape (1, 3) [m]. ``raytrace``: nothing to warm
    (numpy on the paths traced before the run)."""
    if channel == "raytrace":
        return
    if channel == "ideal":
        window_edge_path(anchor_m, node_m, window_height_m=scenario.building.window_height_m)
    else:
        # what first_arrivals runs (its compiled detector)
        pair_first_arrival(anchor_m, node_m, building=scenario.building, radio=scenario.radio)
