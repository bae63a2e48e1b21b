"""Anchor and node trajectories for emulation: static, hover, orbit, waypoints.

Every trajectory is a frozen dataclass with two vectorised methods,

- ``position_m(t_s)``: ``t_s`` of any shape ``(...)`` [s] -> positions ``(..., 3)`` [m],
- ``velocity_m_s(t_s)``: ``(...)`` [s] -> velocities ``(..., 3)`` [m/s],

so the emulator can evaluate all epochs of a run in one call. Times are seconds since the
start of the run (``t_s = 0`` is the start; negative times are allowed and extrapolate the
periodic motions backwards, waypoints clamp to the first point).

Kinds (the ``kind`` key in a scenario file)
------------------------------------------
``static``
    Fixed point ``position_m``.
``hover``
    A UAV holding a point ``center_m`` with a small deterministic wander: a Lissajous figure
    of amplitude ``wander_m`` in x, y and ``wander_m / 2`` in z, with incommensurate periods
    around ``period_s`` (so it never exactly repeats over a short run). ``wander_m = 0`` is
    static.
``orbit``
    Circle of ``radius_m`` about ``center_m`` in a horizontal plane, one turn every
    ``period_s`` seconds, starting at angle ``phase_deg`` (0 = +x from the centre),
    counter-clockwise seen from above unless ``clockwise``.
``waypoints``
    Piecewise-linear path through ``points_m`` (K >= 2 rows), reached at times ``times_s``
    (strictly increasing, first 0) or, if ``times_s`` is omitted, at constant ``speed_m_s``.
    Before the first time the object waits at the first point, after the last it stays at
    the last point, unless ``loop`` is true: then it returns to the first point at the same
    speed as its last leg (or ``speed_m_s``) and repeats forever. Stairs between floors are
    simply waypoints with changing z (e.g. a 3 m climb over a 5 m horizontal run).

Use :func:`trajectory_from_dict` to build one from a plain mapping (what ``tomllib``
returns); errors are :class:`ValueError` with the offending key in the message.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "Hover",
    "Orbit",
    "Static",
    "Trajectory",
    "Waypoints",
    "trajectory_from_dict",
]

FloatArray = NDArray[np.float64]

#: Ratios of the hover wander periods in x, y, z to ``period_s`` (incommensurate).
_HOVER_RATIOS = (1.0, 1.3819660112501051, 0.7236067977499789)


def _vec3(value: Any, name: str) -> tuple[float, float, float]:
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise ValueError(f"{name}: expected 3 finite numbers [x, y, z] in metres, got {value!r}")
    return (float(arr[0]), float(arr[1]), float(arr[2]))


@dataclass(frozen=True)
class Static:
    """A fixed point.

    Attributes
    ----------
    position: tuple of 3 float [m]
    """

    position: tuple[float, float, float]
    kind: str = field(default="static", init=False)

    def position_m(self, t_s: ArrayLike) -> FloatArray:
        """Position at times ``t_s`` ``(...)`` [s] -> ``(..., 3)`` [m]."""
        t = np.asarray(t_s, dtype=np.float64)
        return np.broadcast_to(np.asarray(self.position), (*t.shape, 3)).copy()

    def velocity_m_s(self, t_s: ArrayLike) -> FloatArray:
        """Velocity (zero) at times ``t_s`` ``(...)`` [s] -> ``(..., 3)`` [m/s]."""
        t = np.asarray(t_s, dtype=np.float64)
        return np.zeros((*t.shape, 3))

    def to_dict(self) -> dict[str, Any]:
        return {"kind": "static", "position_m": list(self.position)}


@dataclass(frozen=True)
class Hover:
    """Hovering about ``center`` with a small Lissajous wander.

    ``p(t) = c + (a sin(w_x t + f), a sin(w_y t + 2f), a/2 sin(w_z t + 3f))`` with
    ``w_i = 2 pi / (period_s * r_i)``, ``r = (1, 1.382, 0.724)`` and ``f = phase_deg``.

    Attributes
    ----------
    center : tuple of 3 float [m]
    wander_m : float [m]
        Amplitude ``a`` of the horizontal wander (vertical is ``a / 2``).
    period_s : float [s]
        Base period of the wander.
    phase_deg : float [deg]
        Phase offset (use different phases for different UAVs).
    """

    center: tuple[float, float, float]
    wander_m: float = 0.3
    period_s: float = 20.0
    phase_deg: float = 0.0
    kind: str = field(default="hover", init=False)

    def _omega(self) -> FloatArray:
        return 2.0 * np.pi / (self.period_s * np.asarray(_HOVER_RATIOS))

    def _amp(self) -> FloatArray:
        return self.wander_m * np.array([1.0, 1.0, 0.5])

    def _phase(self) -> FloatArray:
        return np.deg2rad(self.phase_deg) * np.array([1.0, 2.0, 3.0])

    def position_m(self, t_s: ArrayLike) -> FloatArray:
        """Position at times ``t_s`` ``(...)`` [s] -> ``(..., 3)`` [m]."""
        t = np.asarray(t_s, dtype=np.float64)[..., None]
        return np.asarray(self.center) + self._amp() * np.sin(self._omega() * t + self._phase())

    def velocity_m_s(self, t_s: ArrayLike) -> FloatArray:
        """Velocity at times ``t_s`` ``(...)`` [s] -> ``(..., 3)`` [m/s]."""
        t = np.asarray(t_s, dtype=np.float64)[..., None]
        w = self._omega()
        return self._amp() * w * np.cos(w * t + self._phase())

    def to_dict(self) -> dict[str, Any]:
        return {
            "kind": "hover",
            "center_m": list(self.center),
            "wander_m": self.wander_m,
            "period_s": self.period_s,
            "phase_deg": self.phase_deg,
        }


@dataclass(frozen=True)
class Orbit:
    """Horizontal circle about ``center``.

    Attributes
    ----------
    center : tuple of 3 float [m]
    radius_m : float [m]
    period_s : float [s]
        Time for one full turn.
    phase_deg : float [deg]
        Angle at ``t = 0`` measured from +x towards +y.
    clockwise : bool
        Direction seen from above (+z); default counter-clockwise.
    """

    center: tuple[float, float, float]
    radius_m: float
    period_s: float
    phase_deg: float = 0.0
    clockwise: bool = False
    kind: str = field(default="orbit", init=False)

    def _angle(self, t: FloatArray) -> FloatArray:
        sign = -1.0 if self.clockwise else 1.0
        return np.deg2rad(self.phase_deg) + sign * 2.0 * np.pi * t / self.period_s

    def position_m(self, t_s: ArrayLike) -> FloatArray:
        """Position at times ``t_s`` ``(...)`` [s] -> ``(..., 3)`` [m]."""
        t = np.asarray(t_s, dtype=np.float64)
        a = self._angle(t)
        c = np.asarray(self.center)
        return np.stack(
            [c[0] + self.radius_m * np.cos(a), c[1] + self.radius_m * np.sin(a),
             np.full_like(a, c[2])],
            axis=-1,
        )

    def velocity_m_s(self, t_s: ArrayLike) -> FloatArray:
        """Velocity at times ``t_s`` ``(...)`` [s] -> ``(..., 3)`` [m/s]."""
        t = np.asarray(t_s, dtype=np.float64)
        a = self._angle(t)
        sign = -1.0 if self.clockwise else 1.0
        w = sign * 2.0 * np.pi / self.period_s
        return np.stack(
            [-self.radius_m * w * np.sin(a), self.radius_m * w * np.cos(a), np.zeros_like(a)],
            axis=-1,
        )

    def to_dict(self) -> dict[str, Any]:
        return {
            "kind": "orbit",
            "center_m": list(self.center),
            "radius_m": self.radius_m,
            "period_s": self.period_s,
            "phase_deg": self.phase_deg,
            "clockwise": self.clockwise,
        }


@dataclass(frozen=True)
class Waypoints:
    """Piecewise-linear motion through waypoints.

    Attributes
    ----------
    points : tuple of K tuples of 3 float [m]
        Waypoints, K >= 2.
    times : tuple of K float [s]
        Arrival time at each waypoint, strictly increasing, ``times[0] == 0``.
    loop : bool
        Return to the first point and repeat (period = ``times[-1]`` + return leg).
    return_time_s : float [s]
        Duration of the closing leg back to the first point when ``loop`` (ignored otherwise).
    """

    points: tuple[tuple[float, float, float], ...]
    times: tuple[float, ...]
    loop: bool = False
    return_time_s: float = 0.0
    kind: str = field(default="waypoints", init=False)

    def _knots(self) -> tuple[FloatArray, FloatArray]:
        p = np.asarray(self.points, dtype=np.float64)
        t = np.asarray(self.times, dtype=np.float64)
        if self.loop:
            p = np.concatenate([p, p[:1]], axis=0)
            t = np.concatenate([t, [t[-1] + self.return_time_s]])
        return p, t

    @property
    def duration_s(self) -> float:
        """Time of the last knot (one period when looping) [s]."""
        return float(self._knots()[1][-1])

    def _local_time(self, t_s: ArrayLike) -> FloatArray:
        _p, knots = self._knots()
        t = np.asarray(t_s, dtype=np.float64)
        if self.loop:
            return np.mod(t, knots[-1])
        return t

    def position_m(self, t_s: ArrayLike) -> FloatArray:
        """Position at times ``t_s`` ``(...)`` [s] -> ``(..., 3)`` [m]."""
        p, knots = self._knots()
        t = self._local_time(t_s)
        return np.stack([np.interp(t, knots, p[:, i]) for i in range(3)], axis=-1)

    def velocity_m_s(self, t_s: ArrayLike) -> FloatArray:
        """Velocity at times ``t_s`` ``(...)`` [s] -> ``(..., 3)`` [m/s].

        Piecewise constant; at a knot the velocity of the leg starting there is returned;
        zero before the start and after the end of a non-looping path.
        """
        p, knots = self._knots()
        t = self._local_time(t_s)
        seg_v = np.diff(p, axis=0) / np.diff(knots)[:, None]
        idx = np.searchsorted(knots, t, side="right") - 1
        inside = (idx >= 0) & (idx < len(knots) - 1)
        v = seg_v[np.clip(idx, 0, len(seg_v) - 1)]
        return np.where(inside[..., None], v, 0.0)

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {
            "kind": "waypoints",
            "points_m": [list(p) for p in self.points],
            "times_s": list(self.times),
            "loop": self.loop,
        }
        if self.loop:
            d["return_time_s"] = self.return_time_s
        return d


Trajectory = Static | Hover | Orbit | Waypoints


def _pos(key: str, *, cond: str, ok: bool, value: Any) -> None:
    if not ok:
        raise ValueError(f"{key}: {cond}, got {value!r}")


def _number(d: Mapping[str, Any], key: str, default: float | None = None) -> float:
    if key not in d:
        if default is None:
            raise ValueError(f"{key}: required")
        return default
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, int | float) or not np.isfinite(v):
        raise ValueError(f"{key}: expected a finite number, got {v!r}")
    return float(v)


_KEYS = {
    "static": {"kind", "position_m"},
    "hover": {"kind", "center_m", "wander_m", "period_s", "phase_deg"},
    "orbit": {"kind", "center_m", "radius_m", "period_s", "phase_deg", "clockwise"},
    "waypoints": {"kind", "points_m", "times_s", "speed_m_s", "loop", "return_time_s"},
}


def trajectory_from_dict(d: Mapping[str, Any]) -> Trajectory:
    """Build a trajectory from a mapping with a ``kind`` key (see the module docstring).

    Raises
    ------
    ValueError
        Naming the offending key relative to the mapping, e.g. ``"radius_m: must be > 0 m"``.
    """
    if not isinstance(d, Mapping):
        raise ValueError(f"expected a table with a 'kind' key, got {d!r}")
    kind = d.get("kind")
    if kind not in _KEYS:
        raise ValueError(f"kind: must be one of {sorted(_KEYS)}, got {kind!r}")
    unknown = set(d) - _KEYS[kind]
    if unknown:
        raise ValueError(
            f"{sorted(unknown)[0]}: unknown key for a {kind} trajectory "
            f"(allowed: {sorted(_KEYS[kind])})"
        )
    if kind == "static":
        if "position_m" not in d:
            raise ValueError("position_m: required")
        return Static(_vec3(d["position_m"], "position_m"))
    if kind == "hover":
        if "center_m" not in d:
            raise ValueError("center_m: required")
        wander = _number(d, "wander_m", 0.3)
        period = _number(d, "period_s", 20.0)
        _pos("wander_m", cond="must be >= 0 m", ok=wander >= 0, value=wander)
        _pos("period_s", cond="must be > 0 s", ok=period > 0, value=period)
        return Hover(_vec3(d["center_m"], "center_m"), wander, period, _number(d, "phase_deg", 0.0))
    if kind == "orbit":
        if "center_m" not in d:
            raise ValueError("center_m: required")
        radius = _number(d, "radius_m")
        period = _number(d, "period_s")
        _pos("radius_m", cond="must be > 0 m", ok=radius > 0, value=radius)
        _pos("period_s", cond="must be > 0 s", ok=period > 0, value=period)
        cw = d.get("clockwise", False)
        if not isinstance(cw, bool):
            raise ValueError(f"clockwise: expected true or false, got {cw!r}")
        return Orbit(_vec3(d["center_m"], "center_m"), radius, period,
                     _number(d, "phase_deg", 0.0), cw)
    # waypoints
    raw = d.get("points_m")
    if raw is None:
        raise ValueError("points_m: required (a list of [x, y, z] in metres)")
    if not isinstance(raw, list | tuple) or len(raw) < 2:
        raise ValueError(f"points_m: need at least 2 waypoints, got {raw!r}")
    pts = tuple(_vec3(p, f"points_m[{i}]") for i, p in enumerate(raw))
    loop = d.get("loop", False)
    if not isinstance(loop, bool):
        raise ValueError(f"loop: expected true or false, got {loop!r}")
    p = np.asarray(pts)
    if "times_s" in d:
        if "speed_m_s" in d:
            raise ValueError("speed_m_s: give either times_s or speed_m_s, not both")
        times = np.asarray(d["times_s"], dtype=np.float64)
        if times.shape != (len(pts),):
            raise ValueError(f"times_s: need one time per waypoint ({len(pts)}), got {d['times_s']!r}")
        if times[0] != 0.0 or np.any(np.diff(times) <= 0) or not np.all(np.isfinite(times)):
            raise ValueError(f"times_s: must start at 0 and strictly increase, got {d['times_s']!r}")
        last_leg = float(np.linalg.norm(p[-1] - p[-2]))
        speed = last_leg / float(times[-1] - times[-2]) if last_leg > 0 else 1.0
    else:
        speed = _number(d, "speed_m_s", 1.0)
        _pos("speed_m_s", cond="must be > 0 m/s", ok=speed > 0, value=speed)
        seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
        if np.any(seg == 0):
            raise ValueError("points_m: consecutive waypoints must differ")
        times = np.concatenate([[0.0], np.cumsum(seg / speed)])
    ret = float(np.linalg.norm(p[0] - p[-1])) / speed
    if loop:
        ret = _number(d, "return_time_s", ret if ret > 0 else 1e-9)
        _pos("return_time_s", cond="must be > 0 s", ok=ret > 0, value=ret)
    return Waypoints(pts, tuple(float(x) for x in times), loop, ret if loop else 0.0)
