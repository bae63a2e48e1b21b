"""What the dashboard draws of the building: :class:`BuildingOutline` (a box with one window
band per floor), built from a scenario building or a plain mapping."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["BuildingOutline", "FloatArray"]

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class BuildingOutline:
    """What the dashboard draws of the building (a box with one window band per floor).

    Attributes
    ----------
    x_min_m, x_max_m : float [m]
        Extent of the facade (and of the horizontal window edges) along x.
    depth_m : float [m]
        Depth of the building into y > 0.
    n_floors : int
        Number of modelled floors (floor ``k`` spans ``z in first + [k h, (k + 1) h]``).
    floor_height_m : float [m]
        Storey height ``h``.
    sill_height_m : float [m]
        Height of the window sill (lower window edge) above each floor.
    window_height_m : float [m]
        Window height ``w``: the upper (lintel) edge is at ``sill + w`` above the floor.
    first_floor_z_m : float [m]
        Height of the lowest modelled floor (floor ``k`` starts at ``first + k h``).
    edge : {"upper", "lower"}
        The window edge the diffraction paths are drawn over: the one the fusion models
        (:func:`diffpos_services.dashboard.scenario.building_of_scenario` applies the fusion's
        ``--edge auto`` rule). Not part of equality: it is a property of the run's model, not
        of the building's geometry.
    walls : tuple of (axis, position_m, (lo_m, hi_m))
        Interior walls on every floor (the scenario's partitions): ``axis`` ``"x"`` is the
        plane ``x = position_m`` spanning ``y`` in ``(lo, hi)``, ``"y"`` the plane ``y =
        position_m`` spanning ``x``. Drawn on the floor plans; not part of equality.
    stairs : tuple of (x0_m, x1_m, y0_m, y1_m, floor_lo, floor_hi)
        Stair footprints between floors ``floor_lo`` and ``floor_hi`` (the scenario has no
        stairs of its own: :func:`diffpos_services.dashboard.scenario.building_of_scenario`
        takes them from the legs of its responders' trajectories that change floor). Not
        part of equality.
    """

    x_min_m: float
    x_max_m: float
    depth_m: float
    n_floors: int
    floor_height_m: float
    sill_height_m: float
    window_height_m: float
    first_floor_z_m: float = 0.0
    edge: Literal["upper", "lower"] = field(default="upper", compare=False)
    walls: tuple[tuple[str, float, tuple[float, float]], ...] = field(default=(), compare=False)
    stairs: tuple[tuple[float, float, float, float, int, int], ...] = field(
        default=(), compare=False)

    def __post_init__(self) -> None:
        if not self.x_max_m > self.x_min_m:
            raise ValueError("BuildingOutline: x_max_m must be larger than x_min_m")
        for name in ("depth_m", "floor_height_m", "window_height_m"):
            if not getattr(self, name) > 0:
                raise ValueError(f"BuildingOutline: {name} must be > 0")
        if self.n_floors < 1:
            raise ValueError("BuildingOutline: n_floors must be >= 1")
        if (
            self.sill_height_m < 0
            or self.sill_height_m + self.window_height_m > self.floor_height_m
        ):
            raise ValueError(
                "BuildingOutline: need 0 <= sill_height_m and sill + window height <= floor height"
            )
        if self.edge not in ("upper", "lower"):
            raise ValueError("BuildingOutline: edge must be 'upper' or 'lower'")

    @classmethod
    def from_object(cls, obj: Any) -> BuildingOutline:
        """Build from a scenario building (duck-typed) or a plain mapping.

        Accepted spellings: ``x_min_m``/``x_max_m`` or ``x_extent_m``/``edge_x_m`` (a pair) or
        ``width_m`` (centred on ``center_x_m``, default 0); ``depth_m``; ``n_floors``/``floors``;
        ``floor_height_m``; ``sill_height_m``; ``window_height_m``.
        """
        if isinstance(obj, BuildingOutline):
            return obj

        def get(*names: str, default: Any = None) -> Any:
            for name in names:
                if isinstance(obj, Mapping) and name in obj:
                    return obj[name]
                if not isinstance(obj, Mapping) and hasattr(obj, name):
                    return getattr(obj, name)
            if default is not None:
                return default
            raise ValueError(f"building: missing field {' / '.join(names)}")

        extent = get("x_extent_m", "edge_x_m", "window_x_m", default=False)
        if extent is not False and extent is not None:
            x0, x1 = float(min(extent)), float(max(extent))
        elif (isinstance(obj, Mapping) and "x_min_m" in obj) or hasattr(obj, "x_min_m"):
            x0, x1 = float(get("x_min_m")), float(get("x_max_m"))
        else:
            width = float(get("width_m"))
            center = float(get("center_x_m", default=0.0))
            x0, x1 = center - 0.5 * width, center + 0.5 * width
        floors = get("n_floors", "floors", "num_floors")
        n_floors = len(floors) if isinstance(floors, Sequence) else int(floors)
        parts = get("partitions", "walls", default=())
        return cls(
            walls=tuple(_wall(w) for w in parts),
            x_min_m=x0,
            x_max_m=x1,
            depth_m=float(get("depth_m")),
            n_floors=n_floors,
            floor_height_m=float(get("floor_height_m")),
            sill_height_m=float(get("sill_height_m", "window_sill_m")),
            window_height_m=float(get("window_height_m")),
            first_floor_z_m=float(get("first_floor_z_m", default=0.0)),
        )

    @property
    def top_z_m(self) -> float:
        """Ceiling of the highest modelled floor [m]."""
        return self.first_floor_z_m + self.n_floors * self.floor_height_m

    def floor_of(self, z_m: ArrayLike) -> NDArray[np.int64]:
        """Floor index of heights ``z_m`` [m] (clipped to the building; -1 where z is NaN)."""
        z = np.asarray(z_m, dtype=np.float64)
        k = np.floor(
            (np.where(np.isfinite(z), z, 0.0) - self.first_floor_z_m) / self.floor_height_m
        )
        k = np.clip(k, 0, self.n_floors - 1).astype(np.int64)
        return np.where(np.isfinite(z), k, -1)

    def upper_edge_z_m(self, floor_index: ArrayLike) -> FloatArray:
        """Height of the upper (lintel) window edge of each floor [m]."""
        k = np.asarray(floor_index, dtype=np.float64)
        return (
            self.first_floor_z_m
            + k * self.floor_height_m
            + self.sill_height_m
            + self.window_height_m
        )


    def lower_edge_z_m(self, floor_index: ArrayLike) -> FloatArray:
        """Height of the lower (sill) window edge of each floor [m]."""
        k = np.asarray(floor_index, dtype=np.float64)
        return self.first_floor_z_m + k * self.floor_height_m + self.sill_height_m

    def edge_z_m(self, floor_index: ArrayLike) -> FloatArray:
        """Height of the modelled window edge (:attr:`edge`) of each floor [m]."""
        if self.edge == "lower":
            return self.lower_edge_z_m(floor_index)
        return self.upper_edge_z_m(floor_index)


def _wall(w: Any) -> tuple[str, float, tuple[float, float]]:
    """``(axis, position_m, (lo, hi))`` of a scenario partition (dataclass or mapping)."""
    get = (lambda k: w[k]) if isinstance(w, Mapping) else (lambda k: getattr(w, k))
    lo, hi = (float(v) for v in get("span_m"))
    return str(get("axis")), float(get("position_m")), (min(lo, hi), max(lo, hi))
