"""The upper/lower window-edge power ratio swept over the anchor's elevation (Theorem 3).

The anchor stays at ``(0, -anchor_distance_m, anchor_height_m)``; the node's floor moves so
that the window centre is seen from the anchor at elevation theta, and the node sits at the
window mid-height (or ``delta_m`` above it, Case-2) at depth ``y_n`` behind the wall. For
every depth x angle: Theorem 3's approximation, the exact ratio of the field model
(:func:`diffpos.channel.gtd.power_ratio_exact`) and whether the node sees the anchor directly through
the window. Pure numerics (what ``diffpos power-ratio`` plots and tabulates).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from diffpos.channel import gtd

__all__ = ["PowerRatioSweep", "Sweep", "compute_sweep", "first_crossing_deg"]


@dataclass(frozen=True)
class PowerRatioSweep:
    """What to sweep.

    Attributes
    ----------
    depths_m : tuple of float [m]
        Node depths ``y_n`` behind the wall, one exact curve each.
    window_height_m : float [m]
    anchor_distance_m, anchor_height_m : float [m]
        ``|y_a|`` in front of the wall and ``z_a``.
    delta_m : float [m]
        Case-2 offset: node this far above the window centre.
    frequency_hz : float [Hz]
    coefficients : {"utd", "keller"}
    spreading : {"spherical", "paper"}
    e0 : tuple of 3 float
        Transmit polarisation vector.
    theta_min_deg, theta_max_deg, theta_step_deg : float [deg]
    """

    depths_m: tuple[float, ...] = (2.0, 5.0, 10.0, 20.0)
    window_height_m: float = 1.5
    anchor_distance_m: float = 20.0
    anchor_height_m: float = 1.0
    delta_m: float = 0.0
    frequency_hz: float = 28e9
    coefficients: str = "utd"
    spreading: str = "spherical"
    e0: tuple[float, float, float] = (1.0, 0.0, 0.0)
    theta_min_deg: float = 2.0
    theta_max_deg: float = 90.0
    theta_step_deg: float = 0.25


@dataclass(frozen=True)
class Sweep:
    """Result of the sweep: angles (T,), depths (D,), ratios (D, T) (linear).

    ``los`` (D, T) is True where the node sees the anchor directly through the window opening
    (there the direct path, not a diffraction, arrives first).
    """

    theta_deg: np.ndarray
    depth_m: np.ndarray
    window_center_z_m: np.ndarray
    node_z_m: np.ndarray
    ratio_approx: np.ndarray
    ratio_exact: np.ndarray
    los: np.ndarray


def compute_sweep(cfg: PowerRatioSweep) -> Sweep:
    """Run the sweep (vectorised over depths x angles)."""
    n_steps = round((cfg.theta_max_deg - cfg.theta_min_deg) / cfg.theta_step_deg)
    theta_deg = np.linspace(cfg.theta_min_deg, cfg.theta_max_deg, n_steps + 1)
    depth = np.asarray(cfg.depths_m, dtype=np.float64)
    anchor, node = gtd.elevation_sweep_positions(
        np.deg2rad(theta_deg)[None, :],
        depth[:, None],
        anchor_distance_m=cfg.anchor_distance_m,
        anchor_height_m=cfg.anchor_height_m,
        delta_m=cfg.delta_m,
    )
    exact = gtd.power_ratio_exact(
        anchor,
        node,
        window_height_m=cfg.window_height_m,
        e0=np.asarray(cfg.e0, dtype=np.float64),
        delta_m=cfg.delta_m,
        frequency_hz=cfg.frequency_hz,
        coefficients=cfg.coefficients,
        spreading=cfg.spreading,
    )
    # direct anchor -> node line through the window opening (between the two edges)?
    y_a, z_a = anchor[..., 1], anchor[..., 2]
    y_n, z_n = node[..., 1], node[..., 2]
    z_cross = z_a + (z_n - z_a) * (-y_a) / (y_n - y_a)
    z_centre = z_n - cfg.delta_m
    los = np.abs(z_cross - z_centre) < 0.5 * cfg.window_height_m
    return Sweep(
        theta_deg=theta_deg,
        los=los,
        depth_m=depth,
        window_center_z_m=node[0, :, 2] - cfg.delta_m,
        node_z_m=node[0, :, 2],
        ratio_approx=gtd.power_ratio_approx(np.deg2rad(theta_deg)),
        ratio_exact=exact,
    )


def first_crossing_deg(theta_deg: np.ndarray, value_db: np.ndarray, level_db: float) -> float:
    """Smallest angle where ``value_db`` falls below ``level_db`` (linear interpolation) [deg].

    NaN if it never does on the grid; ``theta_deg[0]`` if it starts below.
    """
    below = np.nonzero(value_db < level_db)[0]
    if below.size == 0:
        return float("nan")
    i = int(below[0])
    if i == 0:
        return float(theta_deg[0])
    t0, t1 = theta_deg[i - 1], theta_deg[i]
    v0, v1 = value_db[i - 1], value_db[i]
    return float(t0 + (level_db - v0) * (t1 - t0) / (v1 - v0))
