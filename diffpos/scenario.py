"""Scenario model: building, radio, anchors and nodes, validated from a plain dict.

A scenario is what ``tomllib`` returns for a scenario file (``scenarios/paper.toml`` is the
documented example), turned into frozen dataclasses by :meth:`Scenario.from_dict`. Every
problem raises :class:`ScenarioError` whose message starts with the field path and says what
is allowed, e.g. ``anchors[1].position_m: y=15.0 is inside the building (anchors must be
outside, y < 0)``. No file I/O here (see ``diffpos_services.scenario_io.load_scenario``).

Physical limits (a number outside them is a typo or garbage, never a building; the error
names the field and the limit):

- every coordinate (anchor and node positions along their whole trajectory, ``center_x_m``,
  ``first_floor_z_m``, partition spans) within ``|c| <= 100 km`` (:data:`MAX_COORDINATE_M`);
- every building dimension (``width_m``, ``depth_m``, ``floor_height_m``, wall/slab/partition
  thicknesses) and the total height ``n_floors * floor_height_m`` at most 10 km
  (:data:`MAX_BUILDING_SIZE_M`; ``sill_height_m + window_height_m`` must fit in a floor);
- ``n_floors`` in [1, 200] (:data:`MAX_FLOORS`);
- at most 256 anchors (:data:`MAX_ANCHORS`, the fusion's ``max_anchors``), 100,000 listed
  nodes (:data:`MAX_NODES`, the fusion's ``max_nodes``), 10^7 positions of ``[nodes.grid]``
  (:data:`MAX_GRID_POSITIONS`: 240 MB as an array), 1,024 partitions (:data:`MAX_PARTITIONS`) and 10,000 waypoints per
  trajectory (:data:`MAX_WAYPOINTS`); a count beyond a limit is refused before any entry is
  parsed, naming the limit;
- two anchors whose positions stay within 1 cm of each other (:data:`MIN_ANCHOR_SEPARATION_M`)
  over the first hour are co-located: rejected, naming both ids (they add no geometry). The
  check costs O(n log n) in the anchor count (sorting 1 cm cells of the positions at t = 0
  finds the pairs within 1 cm then; only those are compared over the hour).

(The file-level limits, size and nesting depth, are ``diffpos_services.scenario_io``'s.)

Fewer than 3 anchors is valid (e.g. to study a link) but no 3D fix is ever possible: it is
reported in :attr:`Scenario.warnings` (the core prints nothing; the loader surfaces them).

Building frame (DEVELOPING.md): the facade with the windows is the plane ``y = 0``, the
inside is ``0 < y < depth``, ``x`` runs along the window edges, ``z`` is up (0 = ground).

The paper's building (Appendix "Raytracing Simulation") is only described in words; the
numbers chosen for :func:`default_scenario` and why:

- 5 floors "located above the UAV anchor": floor ``k`` (0-based) has its floor surface at
  ``z = 4 + 3 k`` m (floor height 3 m, so the paper's Case-2 offset ``Delta = 1.5 m`` is half a
  floor, as the paper states). The lowest floor is at the height of the highest anchor (4 m),
  so every floor and every window is above every anchor; the facade below is solid wall.
- Window band on every floor: a continuous opening across the facade (the paper's model has
  no pillars), sill 0.75 m, height ``w = 1.5 m``; its centre (0.75 + 0.75 = 1.5 m above the
  floor) is the node's nominal height, i.e. mid-floor, which is the paper's Assumption 1.
- Width 40 m (window edges span ``x`` in [-20, 20]), depth 22.5 m.
- Exterior walls, floor slabs and ground of ITU-R P.2040 "concrete" (0.2 m walls, 0.3 m
  slabs: about 90 dB and 135 dB of loss at 28 GHz, see ``diffpos.channel.emulator.slab_loss_db``); the
  windows are plain glass with negligible loss (paper, citing Honcharenko et al.).
- Interior partitions of ITU-R P.2040 "plasterboard", 2 x 12.5 mm (about 6 dB at 28 GHz):
  three walls perpendicular to the facade at ``x = -10, 0, 10`` m and a corridor wall
  parallel to it at ``y = 12`` m.
- Receivers: a 0.5 m grid on each floor at the nominal height, ``x`` in [-19.75, 19.75]
  (80 columns), ``y`` in [0.5, 22] (44 rows): 3,520 per floor, 17,600 in all (the paper has
  17,485 over five floors; its grid is not specified).
- Anchors: the paper's table; anchor 2 is printed as ``(0, 15, 0)`` but anchors are outside
  (``y < 0``), so ``(0, -15, 0)`` is used.
- Radio: 28 GHz, 400 MHz, noise temperature 300 K, 20 dB processing gain, first-arrival
  threshold ``P_max - 15 dB``, x-polarised transmitters (Theorem 3). The paper does not give
  the transmit power or antenna gains; 30 dBm and 0 dBi (isotropic) are assumed.
"""

from __future__ import annotations

import bisect
import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from diffpos.constants import SPEED_OF_LIGHT_M_S
from diffpos.trajectory import Hover, Static, Trajectory, Waypoints, trajectory_from_dict

__all__ = [
    "ITU_MATERIALS",
    "MAX_ANCHORS",
    "MAX_BUILDING_SIZE_M",
    "MAX_COORDINATE_M",
    "MAX_FLOORS",
    "MAX_GRID_POSITIONS",
    "MAX_NODES",
    "MAX_PARTITIONS",
    "MAX_WAYPOINTS",
    "MIN_ANCHOR_SEPARATION_M",
    "AnchorSpec",
    "Building",
    "NodeGrid",
    "NodeSpec",
    "Partition",
    "Radio",
    "Scenario",
    "ScenarioError",
    "default_scenario",
    "first_arrival_edge",
]

#: Largest accepted ``|coordinate|`` of any position in a scenario [m] (100 km).
MAX_COORDINATE_M = 100_000.0
#: Largest accepted building dimension and total building height [m] (10 km).
MAX_BUILDING_SIZE_M = 10_000.0
#: Largest accepted number of floors.
MAX_FLOORS = 200
#: Largest accepted number of anchors (the fusion's ``FusionConfig.max_anchors`` default).
MAX_ANCHORS = 256
#: Largest accepted number of listed nodes (the fusion's ``FusionConfig.max_nodes`` default).
MAX_NODES = 100_000
#: Largest accepted number of ``[nodes.grid]`` positions (computed before the grid is built).
MAX_GRID_POSITIONS = 10_000_000
#: Largest accepted number of interior partitions.
MAX_PARTITIONS = 1024
#: Largest accepted number of waypoints of one trajectory.
MAX_WAYPOINTS = 10_000
#: Anchors closer than this over the whole checked horizon are co-located (rejected) [m].
MIN_ANCHOR_SEPARATION_M = 0.01
#: Horizon over which anchor trajectories are compared for co-location [s].
_COLOCATION_HORIZON_S = 3600.0

FloatArray = NDArray[np.float64]

#: ITU-R P.2040-1 Table 3 material constants ``(a, b, c, d)``: real relative permittivity
#: ``a f^b`` and conductivity ``c f^d`` [S/m] with ``f`` in GHz, and the validity range [GHz].
ITU_MATERIALS: dict[str, tuple[float, float, float, float, float, float]] = {
    "vacuum": (1.0, 0.0, 0.0, 0.0, 0.001, 100.0),
    "concrete": (5.24, 0.0, 0.0462, 0.7822, 1.0, 100.0),
    "brick": (3.91, 0.0, 0.0238, 0.16, 1.0, 40.0),
    "plasterboard": (2.73, 0.0, 0.0085, 0.9395, 1.0, 100.0),
    "wood": (1.99, 0.0, 0.0047, 1.0718, 0.001, 100.0),
    "glass": (6.31, 0.0, 0.0036, 1.3394, 0.1, 100.0),
    "ceiling_board": (1.48, 0.0, 0.0011, 1.0750, 1.0, 100.0),
    "floorboard": (3.66, 0.0, 0.0044, 1.3515, 50.0, 100.0),
    "metal": (1.0, 0.0, 1e7, 0.0, 1.0, 100.0),
}


class ScenarioError(ValueError):
    """Invalid scenario; the message starts with the field path (``anchors[1].position_m``)."""


# --------------------------------------------------------------------------------------------
# dataclasses
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Partition:
    """An interior wall (vertical plane, all floors).

    Attributes
    ----------
    axis : {"x", "y"}
        ``"x"``: the plane ``x = position_m`` (perpendicular to the facade), spanning ``y`` in
        ``span_m``; ``"y"``: the plane ``y = position_m`` (parallel to the facade), spanning
        ``x`` in ``span_m``.
    position_m : float [m]
    span_m : (float, float) [m]
    material : str
        ITU-R P.2040 material name (see :data:`ITU_MATERIALS`).
    thickness_m : float [m]
    loss_db : float or None [dB]
        Transmission loss override; ``None`` computes it from the material at the carrier.
    """

    axis: str
    position_m: float
    span_m: tuple[float, float]
    material: str = "plasterboard"
    thickness_m: float = 0.025
    loss_db: float | None = None


@dataclass(frozen=True)
class Building:
    """Rectangular building with a continuous window band on every floor of its facade.

    Attributes
    ----------
    width_m : float [m]
        Facade width; windows and edges span ``x`` in ``center_x_m +- width_m / 2``.
    center_x_m : float [m]
    depth_m : float [m]
        Inside is ``0 < y < depth_m``.
    n_floors : int
    floor_height_m : float [m]
        Floor-to-floor height ``H``; floor ``k`` has its floor at ``first_floor_z_m + k H`` and
        its ceiling ``H`` higher (slab thickness only matters for losses).
    first_floor_z_m : float [m]
        Height of the lowest modelled floor; the facade below it is solid wall.
    sill_height_m : float [m]
        Window sill above the floor; the window band is ``[sill, sill + w]`` above the floor.
    window_height_m : float [m]
        Window height ``w``.
    windows : {"glass", "open"}
        Plain glass (``glass_loss_db`` per crossing) or open.
    glass_loss_db : float [dB]
    wall_material, slab_material, ground_material, interior_material : str
        ITU-R P.2040 materials of the exterior walls, floor slabs, outside ground and interior
        surfaces (floors, ceilings, back and side walls) used for reflections.
    wall_thickness_m, slab_thickness_m : float [m]
    wall_loss_db, slab_loss_db : float or None [dB]
        Transmission loss overrides; ``None`` computes them from the material.
    partitions : tuple of Partition
    """

    width_m: float = 40.0
    center_x_m: float = 0.0
    depth_m: float = 22.5
    n_floors: int = 5
    floor_height_m: float = 3.0
    first_floor_z_m: float = 4.0
    sill_height_m: float = 0.75
    window_height_m: float = 1.5
    windows: str = "glass"
    glass_loss_db: float = 0.0
    wall_material: str = "concrete"
    wall_thickness_m: float = 0.2
    wall_loss_db: float | None = None
    slab_material: str = "concrete"
    slab_thickness_m: float = 0.3
    slab_loss_db: float | None = None
    ground_material: str = "concrete"
    interior_material: str = "concrete"
    partitions: tuple[Partition, ...] = ()

    @property
    def edge_x_m(self) -> tuple[float, float]:
        """Extent ``(x_1, x_2)`` of the horizontal window edges [m]."""
        h = 0.5 * self.width_m
        return (self.center_x_m - h, self.center_x_m + h)

    @property
    def top_z_m(self) -> float:
        """Ceiling of the highest floor [m]."""
        return self.first_floor_z_m + self.n_floors * self.floor_height_m

    @property
    def nominal_node_height_m(self) -> float:
        """Node height above its floor at the window's mid-height (Assumption 1) [m]."""
        return self.sill_height_m + 0.5 * self.window_height_m

    def floor_z_m(self, floor: ArrayLike) -> FloatArray:
        """Floor surface height of floor index ``floor`` [m]."""
        return self.first_floor_z_m + np.asarray(floor, dtype=np.float64) * self.floor_height_m

    def floor_index(self, z_m: ArrayLike) -> NDArray[np.int_]:
        """Floor index of heights ``z_m`` (-1 below the first floor, n_floors above the top)."""
        k = np.floor((np.asarray(z_m, dtype=np.float64) - self.first_floor_z_m)
                     / self.floor_height_m)
        return np.clip(k, -1, self.n_floors).astype(int)

    def window_z_m(self, floor: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Lower and upper window-edge heights of floor ``floor`` [m]."""
        lo = self.floor_z_m(floor) + self.sill_height_m
        return lo, lo + self.window_height_m

    def inside(self, p_m: ArrayLike) -> NDArray[np.bool_]:
        """True where points ``(..., 3)`` are inside the modelled floors of the building."""
        p = np.asarray(p_m, dtype=np.float64)
        x0, x1 = self.edge_x_m
        return ((p[..., 0] > x0) & (p[..., 0] < x1) & (p[..., 1] > 0)
                & (p[..., 1] < self.depth_m) & (p[..., 2] >= self.first_floor_z_m)
                & (p[..., 2] < self.top_z_m))


@dataclass(frozen=True)
class Radio:
    """Radio parameters shared by all links.

    Attributes
    ----------
    frequency_hz : float [Hz]
    bandwidth_hz : float [Hz]
        Signal bandwidth ``B`` (noise bandwidth and the ranging CRLB's ``beta``).
    tx_power_dbm : float [dBm]
    tx_gain_dbi, rx_gain_dbi : float [dBi]
        Peak antenna gains.
    tx_hpbw_deg, rx_hpbw_deg : float or None [deg]
        Elevation half-power beamwidth of a 3GPP-style pattern
        ``G(theta) = G_peak - min(12 ((theta - peak) / hpbw)^2, 30)`` dB, with the peak at
        ``tx_peak_deg`` / ``rx_peak_deg`` (angles from +z, 90 = horizontal); ``None`` is
        isotropic.
    tx_peak_deg, rx_peak_deg : float [deg]
    polarization : (float, float, float)
        Unit transmit polarisation vector ``E_0`` (default x: parallel to the window edges).
    noise_temperature_k : float [K]
    noise_figure_db : float [dB]
    processing_gain_db : float [dB]
        Added to every path's received power before comparing with ``kTB``.
    fap_threshold_db : float [dB]
        First-arrival threshold below the strongest path: ``T = P_max - fap_threshold_db``.
    detection_snr_db : float [dB]
        An MPC whose SNR (after processing gain) is below this does not exist for the receiver
        (a ray tracer's reporting floor); the first-arrival threshold is never below it.
    range_error_floor_m : float [m]
        Ranging error floor of the chain (calibration of antenna/cable group delays, residual
        multipath merged with the first path inside the ``c / B`` resolution cell, clock
        residue after two-way ranging). A measured range has the standard deviation
        ``sqrt(CRLB^2 + floor^2)``: the CRLB alone (0.2-0.5 mm at 40-50 dB SNR) is reached by no
        real chain. Default 0.05 m: one fifteenth of the 0.75 m resolution cell of a 400 MHz
        chain, the order of the residual error of calibrated wideband (UWB, 500 MHz) two-way
        ranging after antenna-delay calibration (a few cm); set 0 for the ideal CRLB-only
        channel of the paper.
    channel_max_order : int
        Most interactions of the emulated channel's paths (:mod:`diffpos.channel.emulator`):
        2 (default) the 18 first-arrival mechanisms of ``diffpos.paths.mechanisms.MECHANISMS``;
        3 or 4 also the higher-order families of ``diffpos.paths.mechanisms.mechanism_set``
        (e.g. ceiling-floor-ceiling, diffraction then two slab bounces, a ground bounce then
        diffraction), so the emulator's first-arrival mix is not easier than a ray tracer's.
        Changes the emulated channel only, not an estimator's path model.
    """

    frequency_hz: float = 28e9
    bandwidth_hz: float = 400e6
    tx_power_dbm: float = 30.0
    tx_gain_dbi: float = 0.0
    rx_gain_dbi: float = 0.0
    tx_hpbw_deg: float | None = None
    rx_hpbw_deg: float | None = None
    tx_peak_deg: float = 90.0
    rx_peak_deg: float = 90.0
    polarization: tuple[float, float, float] = (1.0, 0.0, 0.0)
    noise_temperature_k: float = 300.0
    noise_figure_db: float = 0.0
    processing_gain_db: float = 20.0
    fap_threshold_db: float = 15.0
    detection_snr_db: float = -10.0
    range_error_floor_m: float = 0.05
    channel_max_order: int = 2

    @property
    def wavelength_m(self) -> float:
        """Carrier wavelength [m]."""
        return SPEED_OF_LIGHT_M_S / self.frequency_hz


@dataclass(frozen=True)
class AnchorSpec:
    """A UAV anchor: id (e.g. ``"uav1"``) and trajectory (static for the paper's study)."""

    id: str
    trajectory: Trajectory

    @property
    def position_m(self) -> FloatArray:
        """Position at ``t = 0`` [m], shape (3,)."""
        return self.trajectory.position_m(0.0)


@dataclass(frozen=True)
class NodeSpec:
    """An indoor node: id (e.g. ``"n01"``) and trajectory."""

    id: str
    trajectory: Trajectory

    @property
    def position_m(self) -> FloatArray:
        """Position at ``t = 0`` [m], shape (3,)."""
        return self.trajectory.position_m(0.0)


@dataclass(frozen=True)
class NodeGrid:
    """A regular grid of static receivers on each floor.

    Attributes
    ----------
    spacing_m : float [m]
        Grid step in x and y.
    x_margin_m : float [m]
        Distance of the first/last column from the side walls.
    y_min_m, y_max_m : float [m]
        First and last row (inside the building); the rows are ``y_min + i spacing``.
    floors : tuple of int or None
        Floor indices to fill (default all).
    height_above_floor_m : float or None [m]
        Receiver height above its floor (default the window mid-height, Assumption 1).
    """

    spacing_m: float = 0.5
    x_margin_m: float = 0.25
    y_min_m: float = 0.5
    y_max_m: float = 22.0
    floors: tuple[int, ...] | None = None
    height_above_floor_m: float | None = None

    def positions_m(self, building: Building) -> FloatArray:
        """Receiver positions, floor by floor, then row (y), then column (x): ``(N, 3)`` [m]."""
        x0, x1 = building.edge_x_m
        xs = np.arange(x0 + self.x_margin_m, x1 - self.x_margin_m + 1e-9, self.spacing_m)
        ys = np.arange(self.y_min_m, self.y_max_m + 1e-9, self.spacing_m)
        floors = range(building.n_floors) if self.floors is None else self.floors
        h = (building.nominal_node_height_m if self.height_above_floor_m is None
             else self.height_above_floor_m)
        zs = np.array([float(building.floor_z_m(k)) + h for k in floors])
        z, y, x = np.meshgrid(zs, ys, xs, indexing="ij")
        return np.stack([x.ravel(), y.ravel(), z.ravel()], axis=-1)


@dataclass(frozen=True)
class Scenario:
    """A complete scenario.

    Attributes
    ----------
    name, description : str
    building : Building
    radio : Radio
    anchors : tuple of AnchorSpec
    nodes : tuple of NodeSpec
        Explicit nodes (for emulation); may be empty when ``node_grid`` is given.
    node_grid : NodeGrid or None
        Static receiver grid for studies.
    warnings : tuple of str
        Validation warnings (valid but useless for fixing, e.g. fewer than 3 anchors), each
        starting with the field path; set by :meth:`from_dict`, not compared, not serialised.
    """

    name: str = "paper"
    description: str = ""
    building: Building = field(default_factory=Building)
    radio: Radio = field(default_factory=Radio)
    anchors: tuple[AnchorSpec, ...] = ()
    nodes: tuple[NodeSpec, ...] = ()
    node_grid: NodeGrid | None = None
    warnings: tuple[str, ...] = field(default=(), compare=False)

    # ---------------------------------------------------------------- convenience
    @property
    def anchor_ids(self) -> list[str]:
        return [a.id for a in self.anchors]

    def anchor_positions_m(self, t_s: float = 0.0) -> FloatArray:
        """Anchor positions at time ``t_s``: ``(M, 3)`` [m]."""
        return np.stack([a.trajectory.position_m(t_s) for a in self.anchors])

    def node_positions_m(self, t_s: float = 0.0) -> FloatArray:
        """Receiver positions: the grid if present, else the explicit nodes at ``t_s``.

        Returns
        -------
        ndarray, shape (N, 3) [m]
        """
        if self.node_grid is not None:
            return self.node_grid.positions_m(self.building)
        if not self.nodes:
            return np.zeros((0, 3))
        return np.stack([n.trajectory.position_m(t_s) for n in self.nodes])

    # ---------------------------------------------------------------- (de)serialisation
    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Scenario:
        """Validate a plain mapping (``tomllib`` output) and build the scenario.

        Raises
        ------
        ScenarioError
            With the field path and the allowed values/range in the message.

        Valid scenarios that can never give a fix (fewer than 3 anchors) come back with
        :attr:`warnings` set.
        """
        return _parse_scenario(d)

    def to_dict(self) -> dict[str, Any]:
        """Plain mapping that :meth:`from_dict` accepts (round trip)."""
        b = self.building
        bd: dict[str, Any] = {
            k: getattr(b, k) for k in _BUILDING_FIELDS if getattr(b, k) is not None
        }
        bd["partitions"] = [
            {k: getattr(p, k) for k in ("axis", "position_m", "material", "thickness_m")}
            | {"span_m": list(p.span_m)}
            | ({} if p.loss_db is None else {"loss_db": p.loss_db})
            for p in b.partitions
        ]
        r = self.radio
        rd = {k: getattr(r, k) for k in _RADIO_FIELDS if getattr(r, k) is not None}
        rd["polarization"] = list(r.polarization)
        out: dict[str, Any] = {
            "name": self.name,
            "description": self.description,
            "building": bd,
            "radio": rd,
            "anchors": [{"id": a.id, "trajectory": a.trajectory.to_dict()} for a in self.anchors],
        }
        nodes: dict[str, Any] = {}
        if self.node_grid is not None:
            g = self.node_grid
            gd = {k: getattr(g, k) for k in _GRID_FIELDS if getattr(g, k) is not None}
            if g.floors is not None:
                gd["floors"] = list(g.floors)
            nodes["grid"] = gd
        if self.nodes:
            nodes["list"] = [{"id": n.id, "trajectory": n.trajectory.to_dict()} for n in self.nodes]
        out["nodes"] = nodes
        return out


def default_scenario() -> Scenario:
    """The paper's geometry (see the module docstring for every assumed number)."""
    return Scenario.from_dict(PAPER_DICT)


# --------------------------------------------------------------------------------------------
# parsing and validation
# --------------------------------------------------------------------------------------------

_BUILDING_FIELDS = (
    "width_m", "center_x_m", "depth_m", "n_floors", "floor_height_m", "first_floor_z_m",
    "sill_height_m", "window_height_m", "windows", "glass_loss_db", "wall_material",
    "wall_thickness_m", "wall_loss_db", "slab_material", "slab_thickness_m", "slab_loss_db",
    "ground_material", "interior_material",
)
_RADIO_FIELDS = (
    "frequency_hz", "bandwidth_hz", "tx_power_dbm", "tx_gain_dbi", "rx_gain_dbi",
    "tx_hpbw_deg", "rx_hpbw_deg", "tx_peak_deg", "rx_peak_deg", "noise_temperature_k",
    "noise_figure_db", "processing_gain_db", "fap_threshold_db", "detection_snr_db",
    "range_error_floor_m", "channel_max_order",
)
_GRID_FIELDS = ("spacing_m", "x_margin_m", "y_min_m", "y_max_m", "height_above_floor_m")

#: The paper's scenario as a plain dict (what ``scenarios/paper.toml`` contains).
PAPER_DICT: dict[str, Any] = {
    "name": "paper",
    "description": "Duggal et al., Diffraction-Aided Wireless Positioning: 4 UAVs, 5 floors",
    "building": {
        "partitions": [
            {"axis": "x", "position_m": -10.0, "span_m": [0.0, 22.5]},
            {"axis": "x", "position_m": 0.0, "span_m": [0.0, 22.5]},
            {"axis": "x", "position_m": 10.0, "span_m": [0.0, 22.5]},
            {"axis": "y", "position_m": 12.0, "span_m": [-20.0, 20.0]},
        ],
    },
    "radio": {},
    "anchors": [
        {"id": "uav1", "position_m": [-15.0, -20.0, 1.0]},
        {"id": "uav2", "position_m": [0.0, -15.0, 0.0]},
        {"id": "uav3", "position_m": [0.0, -7.0, 4.0]},
        {"id": "uav4", "position_m": [15.0, -20.0, 1.0]},
    ],
    "nodes": {"grid": {}},
}


def _fail(path: str, msg: str) -> ScenarioError:
    return ScenarioError(f"{path}: {msg}")


def _check_keys(d: Mapping[str, Any], allowed: Sequence[str], path: str) -> None:
    if not isinstance(d, Mapping):
        raise _fail(path, f"expected a table, got {type(d).__name__} {d!r}")
    for k in d:
        if k not in allowed:
            raise _fail(f"{path}.{k}" if path else k,
                        f"unknown key (allowed: {', '.join(sorted(allowed))})")


def _num(d: Mapping[str, Any], key: str, default: float | None, path: str, *,
         lo: float | None = None, hi: float | None = None, lo_open: bool = False,
         allow_none: bool = False) -> float | None:
    p = f"{path}.{key}"
    v = d.get(key, default)
    if v is None:
        if allow_none:
            return None
        raise _fail(p, "required")
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        raise _fail(p, f"expected a finite number, got {v!r}")
    v = float(v)
    lo_s = "-inf" if lo is None else f"{lo:g}"
    hi_s = "inf" if hi is None else f"{hi:g}"
    rng = f"{'(' if lo_open else '['}{lo_s}, {hi_s}]"
    if lo is not None and (v < lo or (lo_open and v == lo)):
        raise _fail(p, f"{v:g} is out of range (allowed {rng})")
    if hi is not None and v > hi:
        raise _fail(p, f"{v:g} is out of range (allowed {rng})")
    return v


def _material(d: Mapping[str, Any], key: str, default: str, path: str) -> str:
    v = d.get(key, default)
    if v not in ITU_MATERIALS:
        raise _fail(f"{path}.{key}", f"unknown material {v!r} (allowed: {', '.join(ITU_MATERIALS)})")
    return v


def _parse_building(d: Mapping[str, Any]) -> Building:
    path = "building"
    _check_keys(d, (*_BUILDING_FIELDS, "partitions"), path)
    dflt = Building()
    n = lambda k, **kw: _num(d, k, getattr(dflt, k), path, **kw)  # noqa: E731
    size = MAX_BUILDING_SIZE_M
    width = n("width_m", lo=0.0, lo_open=True, hi=size)
    depth = n("depth_m", lo=0.0, lo_open=True, hi=size)
    nf = d.get("n_floors", dflt.n_floors)
    if isinstance(nf, bool) or not isinstance(nf, int) or not 1 <= nf <= MAX_FLOORS:
        raise _fail(f"{path}.n_floors", f"expected an integer in [1, {MAX_FLOORS}], got {nf!r}")
    fh = n("floor_height_m", lo=0.0, lo_open=True, hi=size)
    if nf * fh > size:
        raise _fail(f"{path}.floor_height_m",
                    f"n_floors * floor_height_m = {nf * fh:g} m exceeds the building height "
                    f"limit {size:g} m")
    sill = n("sill_height_m", lo=0.0)  # sill + window <= floor height <= 10 km (below)
    w = n("window_height_m", lo=0.0, lo_open=True)
    if sill + w > fh:
        raise _fail(f"{path}.window_height_m",
                    f"sill_height_m + window_height_m = {sill + w:g} m exceeds floor_height_m = "
                    f"{fh:g} m (the window must fit in its floor)")
    windows = d.get("windows", dflt.windows)
    if windows not in ("glass", "open"):
        raise _fail(f"{path}.windows", f"must be 'glass' or 'open', got {windows!r}")
    cx = n("center_x_m", lo=-MAX_COORDINATE_M, hi=MAX_COORDINATE_M)
    x0, x1 = cx - 0.5 * width, cx + 0.5 * width
    parts = []
    raw_parts = d.get("partitions", [])
    if not isinstance(raw_parts, list):
        raise _fail(f"{path}.partitions", "expected an array of tables")
    _check_count(raw_parts, MAX_PARTITIONS, f"{path}.partitions", "partitions", "MAX_PARTITIONS")
    for i, pd in enumerate(raw_parts):
        pp = f"{path}.partitions[{i}]"
        _check_keys(pd, ("axis", "position_m", "span_m", "material", "thickness_m", "loss_db"), pp)
        axis = pd.get("axis")
        if axis not in ("x", "y"):
            raise _fail(f"{pp}.axis", f"must be 'x' (plane x = const) or 'y' (plane y = const), "
                        f"got {axis!r}")
        if axis == "x":
            pos = _num(pd, "position_m", None, pp, lo=x0, hi=x1)
        else:
            pos = _num(pd, "position_m", None, pp, lo=0.0, hi=depth, lo_open=True)
        span = pd.get("span_m")
        arr = np.asarray(span, dtype=float) if isinstance(span, list) else np.zeros(0)
        if arr.shape != (2,) or not np.all(np.isfinite(arr)) or arr[0] >= arr[1]:
            raise _fail(f"{pp}.span_m", f"expected [lo, hi] with lo < hi in metres, got {span!r}")
        if np.any(np.abs(arr) > MAX_COORDINATE_M):
            raise _fail(f"{pp}.span_m", f"{span!r} is out of range (allowed |c| <= "
                        f"{MAX_COORDINATE_M:g} m)")
        parts.append(Partition(
            axis=axis, position_m=pos, span_m=(float(arr[0]), float(arr[1])),
            material=_material(pd, "material", "plasterboard", pp),
            thickness_m=_num(pd, "thickness_m", 0.025, pp, lo=0.0, lo_open=True, hi=size),
            loss_db=_num(pd, "loss_db", None, pp, lo=0.0, allow_none=True),
        ))
    return Building(
        width_m=width, center_x_m=cx, depth_m=depth, n_floors=nf,
        floor_height_m=fh, first_floor_z_m=n("first_floor_z_m", lo=0.0, hi=MAX_COORDINATE_M),
        sill_height_m=sill,
        window_height_m=w, windows=windows, glass_loss_db=n("glass_loss_db", lo=0.0),
        wall_material=_material(d, "wall_material", dflt.wall_material, path),
        wall_thickness_m=n("wall_thickness_m", lo=0.0, lo_open=True, hi=size),
        wall_loss_db=_num(d, "wall_loss_db", None, path, lo=0.0, allow_none=True),
        slab_material=_material(d, "slab_material", dflt.slab_material, path),
        slab_thickness_m=n("slab_thickness_m", lo=0.0, lo_open=True, hi=size),
        slab_loss_db=_num(d, "slab_loss_db", None, path, lo=0.0, allow_none=True),
        ground_material=_material(d, "ground_material", dflt.ground_material, path),
        interior_material=_material(d, "interior_material", dflt.interior_material, path),
        partitions=tuple(parts),
    )


def _parse_radio(d: Mapping[str, Any]) -> Radio:
    path = "radio"
    _check_keys(d, (*_RADIO_FIELDS, "polarization"), path)
    dflt = Radio()
    n = lambda k, **kw: _num(d, k, getattr(dflt, k), path, **kw)  # noqa: E731
    f = n("frequency_hz", lo=1e9, hi=100e9)
    pol = d.get("polarization", "x")
    named = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}
    if isinstance(pol, str):
        if pol not in named:
            raise _fail(f"{path}.polarization", f"must be 'x', 'y', 'z' or [ex, ey, ez], got {pol!r}")
        pol_v = named[pol]
    else:
        arr = np.asarray(pol, dtype=float) if isinstance(pol, list) else np.zeros(0)
        if arr.shape != (3,) or not np.all(np.isfinite(arr)) or np.linalg.norm(arr) == 0:
            raise _fail(f"{path}.polarization",
                        f"must be 'x', 'y', 'z' or a non-zero [ex, ey, ez], got {pol!r}")
        arr = arr / np.linalg.norm(arr)
        pol_v = (float(arr[0]), float(arr[1]), float(arr[2]))
    return Radio(
        frequency_hz=f,
        bandwidth_hz=n("bandwidth_hz", lo=0.0, lo_open=True, hi=0.5 * f),
        tx_power_dbm=n("tx_power_dbm", lo=-50.0, hi=60.0),
        tx_gain_dbi=n("tx_gain_dbi", lo=-30.0, hi=50.0),
        rx_gain_dbi=n("rx_gain_dbi", lo=-30.0, hi=50.0),
        tx_hpbw_deg=_num(d, "tx_hpbw_deg", None, path, lo=0.0, lo_open=True, hi=360.0,
                         allow_none=True),
        rx_hpbw_deg=_num(d, "rx_hpbw_deg", None, path, lo=0.0, lo_open=True, hi=360.0,
                         allow_none=True),
        tx_peak_deg=n("tx_peak_deg", lo=0.0, hi=180.0),
        rx_peak_deg=n("rx_peak_deg", lo=0.0, hi=180.0),
        polarization=pol_v,
        noise_temperature_k=n("noise_temperature_k", lo=0.0, lo_open=True),
        noise_figure_db=n("noise_figure_db", lo=0.0, hi=30.0),
        processing_gain_db=n("processing_gain_db", lo=0.0, hi=80.0),
        fap_threshold_db=n("fap_threshold_db", lo=0.0, lo_open=True, hi=100.0),
        detection_snr_db=n("detection_snr_db", lo=-100.0, hi=100.0),
        range_error_floor_m=n("range_error_floor_m", lo=0.0, hi=10.0),
        channel_max_order=_channel_order(d.get("channel_max_order", dflt.channel_max_order)),
    )


def _channel_order(v: Any) -> int:
    if isinstance(v, bool) or not isinstance(v, int) or v not in (2, 3, 4):
        raise _fail("radio.channel_max_order", f"must be 2, 3 or 4 (integer), got {v!r}")
    return v


#: Grammar of anchor, node and site ids: one Zenoh key chunk (the bus uses ids in key
#: expressions, so a scenario must not admit an id the wire would refuse).
ID_PATTERN = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_\-]{0,63}")


def _id(v: Any, path: str, seen: set[str]) -> str:
    if not isinstance(v, str) or not ID_PATTERN.fullmatch(v):
        raise _fail(path, "expected an id of 1-64 ASCII letters, digits, '_' or '-' (not "
                          f"starting with '-'), got {v!r}")
    if v in seen:
        raise _fail(path, f"duplicate id {v!r}")
    seen.add(v)
    return v


def _trajectory(d: Mapping[str, Any], path: str) -> tuple[Trajectory, str]:
    """Trajectory of an anchor/node table: ``position_m`` (static) or ``trajectory``."""
    if ("position_m" in d) == ("trajectory" in d):
        raise _fail(path, "give exactly one of position_m = [x, y, z] or trajectory = {kind = ...}")
    if "position_m" in d:
        key = f"{path}.position_m"
        arr = np.asarray(d["position_m"], dtype=object)
        try:
            vec = np.asarray(d["position_m"], dtype=float)
        except (TypeError, ValueError):
            vec = np.zeros(0)
        if arr.shape != (3,) or vec.shape != (3,) or not np.all(np.isfinite(vec)):
            raise _fail(key, f"expected [x, y, z] in metres, got {d['position_m']!r}")
        return Static((float(vec[0]), float(vec[1]), float(vec[2]))), key
    key = f"{path}.trajectory"
    raw = d["trajectory"]
    if isinstance(raw, Mapping):
        for name in ("points_m", "times_s"):
            if isinstance(raw.get(name), list):
                _check_count(raw[name], MAX_WAYPOINTS, f"{key}.{name}", "waypoints",
                             "MAX_WAYPOINTS")
    try:
        return trajectory_from_dict(raw), key
    except ValueError as exc:
        msg = str(exc)
        sep = ": " if msg.startswith("expected") else "."
        raise ScenarioError(f"{key}{sep}{msg}") from None


def _sample_points(traj: Trajectory) -> FloatArray:
    """Positions to check a trajectory's path against the building, shape (K, 3) [m]."""
    if isinstance(traj, Waypoints):
        return np.asarray(traj.points)  # the building is convex: the vertices suffice
    if isinstance(traj, Static):
        return traj.position_m(np.zeros(1))
    period = traj.period_s * (2.0 if isinstance(traj, Hover) else 1.0)
    return traj.position_m(np.linspace(0.0, period, 721))


def _check_bounded(pts: FloatArray, traj: Trajectory, key: str) -> None:
    """Every sampled position within ``|c| <= MAX_COORDINATE_M``."""
    bad = np.flatnonzero(~np.all(np.abs(pts) <= MAX_COORDINATE_M, axis=-1))
    if bad.size:
        p = pts[bad[0]]
        where = "" if isinstance(traj, Static) else " (somewhere along its trajectory)"
        raise _fail(key, f"({p[0]:g}, {p[1]:g}, {p[2]:g}){where} is out of range (allowed "
                    f"|x|, |y|, |z| <= {MAX_COORDINATE_M:g} m)")


def _check_anchor(traj: Trajectory, key: str) -> None:
    pts = _sample_points(traj)
    _check_bounded(pts, traj, key)
    bad = np.flatnonzero(pts[:, 1] >= 0.0)
    if bad.size:
        y = pts[bad[0], 1]
        where = "" if isinstance(traj, Static) else " (somewhere along its trajectory)"
        raise _fail(key, f"y={y:g} is inside the building{where} "
                    "(anchors must be outside, y < 0)")
    if np.any(pts[:, 2] < 0.0):
        raise _fail(key, f"z={pts[pts[:, 2] < 0, 2][0]:g} is below the ground (need z >= 0)")


def _check_node(traj: Trajectory, key: str, b: Building) -> None:
    pts = _sample_points(traj)
    _check_bounded(pts, traj, key)
    ok = b.inside(pts)
    if not np.all(ok):
        p = pts[np.flatnonzero(~ok)[0]]
        x0, x1 = b.edge_x_m
        raise _fail(key, f"({p[0]:g}, {p[1]:g}, {p[2]:g}) is outside the building's floors "
                    f"(nodes need {x0:g} < x < {x1:g}, 0 < y < {b.depth_m:g}, "
                    f"{b.first_floor_z_m:g} <= z < {b.top_z_m:g})")


def _parse_grid(d: Mapping[str, Any], b: Building) -> NodeGrid:
    path = "nodes.grid"
    _check_keys(d, (*_GRID_FIELDS, "floors"), path)
    dflt = NodeGrid()
    n = lambda k, **kw: _num(d, k, getattr(dflt, k), path, **kw)  # noqa: E731
    spacing = n("spacing_m", lo=0.05, hi=b.width_m)
    xm = n("x_margin_m", lo=0.0, lo_open=True, hi=0.5 * b.width_m)
    y0 = n("y_min_m", lo=0.0, lo_open=True, hi=b.depth_m)
    y1 = n("y_max_m", lo=y0, hi=b.depth_m)
    if y1 >= b.depth_m:
        raise _fail(f"{path}.y_max_m", f"{y1:g} must be < depth_m = {b.depth_m:g}")
    floors = d.get("floors")
    if floors is not None:
        if (not isinstance(floors, list) or not floors
                or not all(isinstance(k, int) and not isinstance(k, bool) and 0 <= k < b.n_floors
                           for k in floors)):
            raise _fail(f"{path}.floors",
                        f"expected a list of floor indices in [0, {b.n_floors - 1}], got {floors!r}")
        floors = tuple(floors)
    h = _num(d, "height_above_floor_m", None, path, lo=0.0, hi=b.floor_height_m, lo_open=True,
             allow_none=True)
    if h is not None and h >= b.floor_height_m:
        raise _fail(f"{path}.height_above_floor_m", f"{h:g} must be < floor_height_m")
    grid = NodeGrid(spacing, xm, y0, y1, floors, h)
    _check_grid_size(grid, b)
    return grid


def _check_grid_size(g: NodeGrid, b: Building) -> None:
    """The grid's position count (computed, not built) within :data:`MAX_GRID_POSITIONS`."""
    x0, x1 = b.edge_x_m
    cols = max(0, math.floor((x1 - x0 - 2 * g.x_margin_m + 1e-9) / g.spacing_m) + 1)
    rows = max(0, math.floor((g.y_max_m - g.y_min_m + 1e-9) / g.spacing_m) + 1)
    n = cols * rows * (b.n_floors if g.floors is None else len(g.floors))
    if n > MAX_GRID_POSITIONS:
        raise _fail("nodes.grid.spacing_m",
                    f"the grid has {n:,} positions ({cols:,} columns x {rows:,} rows x floors); "
                    f"at most {MAX_GRID_POSITIONS:,} are allowed "
                    "(diffpos.scenario.MAX_GRID_POSITIONS): use a "
                    "coarser spacing_m or fewer floors")


def _check_count(items: Sequence[Any], limit: int, path: str, what: str, name: str) -> None:
    """Refuse a list longer than ``limit`` before any of its entries is parsed."""
    if len(items) > limit:
        raise _fail(path, f"{len(items):,} {what}; at most {limit:,} are allowed "
                    f"(diffpos.scenario.{name})")


def _parse_scenario(d: Mapping[str, Any]) -> Scenario:
    _check_keys(d, ("name", "description", "building", "radio", "anchors", "nodes"), "")
    name = d.get("name", "scenario")
    desc = d.get("description", "")
    if not isinstance(name, str) or not isinstance(desc, str):
        raise _fail("name", "name and description must be strings")
    b = _parse_building(d.get("building", {}))
    r = _parse_radio(d.get("radio", {}))
    raw_anchors = d.get("anchors")
    if not isinstance(raw_anchors, list) or len(raw_anchors) == 0:
        raise _fail("anchors", "need at least one [[anchors]] table (3 or more to fix a 3D position)")
    _check_count(raw_anchors, MAX_ANCHORS, "anchors", "anchors", "MAX_ANCHORS")
    seen: set[str] = set()
    anchors = []
    for i, ad in enumerate(raw_anchors):
        p = f"anchors[{i}]"
        _check_keys(ad, ("id", "position_m", "trajectory"), p)
        aid = _id(ad.get("id", f"uav{i + 1}"), f"{p}.id", seen)
        traj, key = _trajectory(ad, p)
        _check_anchor(traj, key)
        anchors.append(AnchorSpec(aid, traj))
    _check_colocated(anchors)
    warnings = _anchor_warnings(anchors)
    raw_nodes = d.get("nodes", {})
    _check_keys(raw_nodes, ("grid", "list"), "nodes")
    grid = _parse_grid(raw_nodes["grid"], b) if "grid" in raw_nodes else None
    nodes = []
    seen = set()
    raw_list = raw_nodes.get("list", [])
    if not isinstance(raw_list, list):
        raise _fail("nodes.list", "expected an array of tables [[nodes.list]]")
    _check_count(raw_list, MAX_NODES, "nodes.list", "nodes", "MAX_NODES")
    for i, nd in enumerate(raw_list):
        p = f"nodes.list[{i}]"
        _check_keys(nd, ("id", "position_m", "trajectory"), p)
        nid = _id(nd.get("id", f"n{i + 1:02d}"), f"{p}.id", seen)
        traj, key = _trajectory(nd, p)
        _check_node(traj, key, b)
        nodes.append(NodeSpec(nid, traj))
    if grid is None and not nodes:
        raise _fail("nodes", "need a [nodes.grid] table or at least one [[nodes.list]] entry")
    return Scenario(name=name, description=desc, building=b, radio=r, anchors=tuple(anchors),
                    nodes=tuple(nodes), node_grid=grid, warnings=warnings)


def _check_colocated(anchors: list[AnchorSpec]) -> None:
    """Reject two anchors that stay within ``MIN_ANCHOR_SEPARATION_M`` of each other.

    O(n log n) in the anchor count: a pair co-located over the horizon is within the
    separation at t = 0, so the pairs within it then (:func:`_close_pairs`) are the only
    candidates compared along the whole horizon.
    """
    if len(anchors) < 2:
        return
    p0 = np.stack([a.trajectory.position_m(np.zeros(1))[0] for a in anchors])
    pairs = _close_pairs(p0, MIN_ANCHOR_SEPARATION_M)
    if not pairs:
        return
    t = np.linspace(0.0, _COLOCATION_HORIZON_S, 3601)
    cache: dict[int, FloatArray] = {}

    def track(k: int) -> FloatArray:
        if k not in cache:
            cache[k] = anchors[k].trajectory.position_m(t)
        return cache[k]

    for i, j in pairs:  # sorted: the first anchor, then its first partner, as before
        if np.max(np.linalg.norm(track(j) - track(i), axis=-1)) < MIN_ANCHOR_SEPARATION_M:
            raise _fail(f"anchors[{j}]", f"anchor {anchors[j].id!r} is co-located with anchor "
                        f"{anchors[i].id!r} (anchors[{i}]): within {MIN_ANCHOR_SEPARATION_M:g} m "
                        f"of it over the first {_COLOCATION_HORIZON_S:g} s; a second anchor at "
                        "the same place adds no geometry (move or remove one)")


def _close_pairs(p: FloatArray, r: float) -> list[tuple[int, int]]:
    """Index pairs ``i < j`` with ``|p_i - p_j| < r``, sorted: O(n log n + pairs).

    Each point falls in a cube of side ``r``; a close pair lies in the same or a neighbouring
    cube, so the cubes are sorted once and each point looks up the 27 around it by binary
    search (no pairwise distance matrix: 10^6 anchors took 23.7 GB that way).
    """
    cell = np.floor(p / r).astype(np.int64)
    order = np.lexsort(cell.T[::-1])
    keys = [tuple(c) for c in cell[order]]
    out: list[tuple[int, int]] = []
    for i in range(len(p)):
        for off in _NEIGHBOURS:
            key = tuple(cell[i] + off)
            lo = bisect.bisect_left(keys, key)
            hi = bisect.bisect_right(keys, key, lo)
            for j in order[lo:hi].tolist():
                if j > i and float(np.linalg.norm(p[j] - p[i])) < r:
                    out.append((i, j))
    return sorted(out)


_NEIGHBOURS = np.array([(a, b, c) for a in (-1, 0, 1) for b in (-1, 0, 1) for c in (-1, 0, 1)])


def _anchor_warnings(anchors: list[AnchorSpec]) -> tuple[str, ...]:
    if len(anchors) < 3:
        return (f"anchors: only {len(anchors)} anchor(s): no 3D fix is ever possible "
                "(need 3 or more)",)
    return ()


def first_arrival_edge(scenario: Scenario, *, horizon_s: float = 60.0) -> tuple[str, str]:
    """The window edge whose diffracted path arrives first, and why.

    A first-arrival detector picks the earliest path within its threshold. For an anchor
    below a window the diffracted path over the window's *lower* edge is geometrically the
    shorter one, and with the exact UTD field it is only a few dB weaker than the upper-edge
    path the paper models (see ``diffpos power-ratio``), so it is usually the first arrival.
    Returns ``("lower", reason)`` when every anchor stays below the lowest window over
    ``[0, horizon_s]`` [s], else ``("upper", reason)`` (the paper's model).
    """
    t = np.linspace(0.0, max(horizon_s, 0.0), 64)
    top_anchor_z = max(float(np.max(a.trajectory.position_m(t)[..., 2])) for a in scenario.anchors)
    lowest_window_z = float(scenario.building.window_z_m(0)[0])
    if top_anchor_z < lowest_window_z:
        return "lower", (f"every anchor below the lowest window ({top_anchor_z:.1f} m < "
                         f"{lowest_window_z:.2f} m): the lower-edge path arrives first")
    return "upper", "some anchor is not below every window: the paper's upper edge"
