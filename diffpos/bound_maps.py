"""Bound maps: the PEB and z-axis bound over a grid of indoor nodes of a :class:`Scenario`.

For every node of a grid on every floor of the scenario's building, the Cramer-Rao bounds of
the paper's diffraction positioning: PEB = sqrt(tr J^-1) [m] and the z-axis bound
sqrt([J^-1]_zz) [m], where J is the Fisher information of the ranges to all anchors under the
window-edge diffraction path model (upper edge, paper eq. 6 and eq. 15).

Each link's ranging accuracy comes from a simple link budget over the scenario's radio:

    P_rx  = P_tx + G_tx + G_rx + gain of the upper-edge diffracted path
    SNR   = P_rx + processing gain - kTB - noise figure
    sigma = c / sqrt(8 pi^2 B^2 SNR)            (ranging CRLB, SNR linear)

The building, radio and anchors are the scenario's (no second building model); what is
specific to a map (grid step, how the diffracted power is obtained, FIM model) is in
:class:`BoundMapSettings`. Pure numerics: no I/O, no plotting.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from diffpos.bounds import (
    DEFAULT_MAX_CONDITION,
    identifiability,
    path_jacobian,
    position_error_bound,
)
from diffpos.channel.gtd import window_edge_fields
from diffpos.channel.linkbudget import db_to_linear, free_space_path_gain_db, ranging_crlb_m, snr_db
from diffpos.constants import SPEED_OF_LIGHT_M_S
from diffpos.geometry import window_edge_path
from diffpos.scenario import Building, Scenario

__all__ = [
    "BoundMapSettings",
    "FloorResult",
    "compute",
    "explain_non_identifiable",
    "grid_xy_m",
    "node_height_m",
    "path_gain_db",
]


@dataclass(frozen=True)
class BoundMapSettings:
    """What a bound map needs besides the scenario.

    Attributes
    ----------
    grid_step_m : float [m]
        Node grid spacing: ``x = center_x + k * step`` (symmetric about and including the
        facade's centre) and ``y = y_min_m + k * step``, at least half a step inside the walls.
    y_min_m : float [m]
        Distance of the first grid row behind the facade.
    diffraction : {"fixed", "utd"}
        How the diffracted power is obtained: Friis over the path length minus
        ``diffraction_loss_db``, or the UTD field of the upper window edge for x-polarised
        isotropic anchors (:func:`diffpos.channel.gtd.window_edge_fields`).
    diffraction_loss_db : float [dB]
        Fixed extra loss of the diffracted path relative to free space (``"fixed"``).
    model : {"diffraction", "los"}
        Path model of the FIM.
    delta_m : float [m]
        Case-2 offset of the model (0 = Assumption 1).
    max_condition : float
        FIM condition number above which a node is not identifiable (Theorem 2).
    """

    grid_step_m: float = 0.5
    y_min_m: float = 0.5
    diffraction: str = "fixed"
    diffraction_loss_db: float = 20.0
    model: str = "diffraction"
    delta_m: float = 0.0
    max_condition: float = DEFAULT_MAX_CONDITION


@dataclass(frozen=True)
class FloorResult:
    """Bounds of one floor's grid (arrays of shape (ny, nx) unless noted)."""

    floor: int
    z_m: float
    x_m: np.ndarray  # (nx,)
    y_m: np.ndarray  # (ny,)
    peb_m: np.ndarray
    z_bound_m: np.ndarray
    axis_bounds_m: np.ndarray  # (ny, nx, 3)
    identifiable: np.ndarray
    snr_db: np.ndarray  # (ny, nx, M)
    sigma_m: np.ndarray  # (ny, nx, M)


def node_height_m(building: Building, floor: int) -> float:
    """Node height of floor ``floor`` (1-based) at the window's mid-height [m]."""
    return float(building.floor_z_m(floor - 1)) + building.nominal_node_height_m


def grid_xy_m(building: Building, settings: BoundMapSettings) -> tuple[np.ndarray, np.ndarray]:
    """Grid coordinates ``(x, y)`` of the nodes of one floor [m]."""
    step = settings.grid_step_m
    k = np.floor((0.5 * building.width_m - 0.5 * step) / step + 1e-9)
    x = building.center_x_m + np.arange(-k, k + 1) * step
    n_y = np.floor((building.depth_m - 0.5 * step - settings.y_min_m) / step + 1e-9)
    y = settings.y_min_m + np.arange(n_y + 1) * step
    return x, y


def path_gain_db(
    scenario: Scenario,
    settings: BoundMapSettings,
    anchors: np.ndarray,
    nodes: np.ndarray,
    length_m: np.ndarray,
) -> np.ndarray:
    """Gain of the upper-edge diffracted path [dB], shape of ``length_m`` (nodes x anchors).

    ``fixed``: Friis over the unfolded length minus ``diffraction_loss_db``. ``utd``: an
    isotropic x-polarised source with field 1 V/m at 1 m has Friis gain
    ``(lambda / 4 pi)^2 |E|^2`` at a point where its field is ``E``; ``E`` is the UTD field of the
    upper edge (Theorem 3: it dominates for x polarisation).
    """
    b, frequency_hz = scenario.building, scenario.radio.frequency_hz
    if settings.diffraction == "fixed":
        return free_space_path_gain_db(length_m, frequency_hz) - settings.diffraction_loss_db
    e_up, _ = window_edge_fields(
        anchors,
        nodes[..., None, :],
        window_height_m=b.window_height_m,
        delta_m=settings.delta_m,
        e0=(1.0, 0.0, 0.0),
        frequency_hz=frequency_hz,
        edge_x_m=b.edge_x_m,
        coefficients="utd",
    )
    lam = SPEED_OF_LIGHT_M_S / frequency_hz
    with np.errstate(divide="ignore"):
        return 20.0 * np.log10(lam / (4.0 * np.pi)) + 20.0 * np.log10(np.linalg.norm(e_up, axis=-1))


def _link_budget(
    scenario: Scenario, settings: BoundMapSettings, anchors: np.ndarray, nodes: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Per-link SNR [dB] and ranging CRLB [m] of nodes ``(..., 3)`` x anchors."""
    b, radio = scenario.building, scenario.radio
    path = window_edge_path(
        anchors,
        nodes[..., None, :],
        window_height_m=b.window_height_m,
        delta_m=settings.delta_m,
        edge_x_m=b.edge_x_m,
    )
    p_rx = radio.tx_power_dbm + path_gain_db(scenario, settings, anchors, nodes, path.length_m)
    p_rx = p_rx + (radio.tx_gain_dbi + radio.rx_gain_dbi)
    snr = snr_db(
        p_rx,
        bandwidth_hz=radio.bandwidth_hz,
        processing_gain_db=radio.processing_gain_db,
        temperature_k=radio.noise_temperature_k,
        noise_figure_db=radio.noise_figure_db,
    )
    return snr, ranging_crlb_m(db_to_linear(snr), radio.bandwidth_hz)


def compute(scenario: Scenario, settings: BoundMapSettings) -> list[FloorResult]:
    """Bounds for every floor of the grid (vectorised over the nodes of a floor)."""
    b = scenario.building
    anchors = scenario.anchor_positions_m()
    x, y = grid_xy_m(b, settings)
    xx, yy = np.meshgrid(x, y)  # the same grid on every floor
    out = []
    for k in range(1, b.n_floors + 1):
        z = node_height_m(b, k)
        nodes = np.stack([xx, yy, np.full_like(xx, z)], axis=-1)  # (ny, nx, 3)
        snr, sigma = _link_budget(scenario, settings, anchors, nodes)
        bound = position_error_bound(
            anchors,
            nodes,
            sigma,
            b.window_height_m,
            settings.delta_m,
            model=settings.model,
            edge_x_m=b.edge_x_m,
            max_condition=settings.max_condition,
        )
        out.append(
            FloorResult(
                floor=k,
                z_m=z,
                x_m=x,
                y_m=y,
                peb_m=bound.peb_m,
                z_bound_m=bound.z_bound_m,
                axis_bounds_m=bound.axis_bounds_m,
                identifiable=bound.identifiable,
                snr_db=snr,
                sigma_m=sigma,
            )
        )
    return out


def explain_non_identifiable(
    scenario: Scenario, settings: BoundMapSettings, results: list[FloorResult]
) -> list[str]:
    """Why nodes are not identifiable: one line per floor that has any (the first node)."""
    lines = []
    anchors = scenario.anchor_positions_m()
    b = scenario.building
    for r in results:
        bad = np.argwhere(~r.identifiable)
        if bad.size == 0:
            continue
        iy, ix = bad[0]
        node = np.array([r.x_m[ix], r.y_m[iy], r.z_m])
        jac = path_jacobian(
            anchors,
            node,
            model=settings.model,
            window_height_m=b.window_height_m,
            delta_m=settings.delta_m,
            edge_x_m=b.edge_x_m,
        )
        verdict = identifiability(jac, r.sigma_m[iy, ix], max_condition=settings.max_condition)
        lines.append(
            f"floor {r.floor}: {len(bad)} node(s) not identifiable, e.g. at "
            f"({node[0]:g}, {node[1]:g}, {node[2]:g}) m: {verdict.message[0]}"
        )
    return lines
