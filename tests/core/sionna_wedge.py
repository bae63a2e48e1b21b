"""Sionna RT's own UTD wedge coefficient (``RadioMaterial._diffraction_matrix``) for an edge of
a dielectric wall, the independent reference of the channel's edge-diffraction tests
(tests/core/test_channel_wall_edge.py, test_channel_window_edge.py). Needs the optional
ray-tracer extra; the callers skip without it."""

from __future__ import annotations

import numpy as np


def sionna_edge_db(src: np.ndarray, obs: np.ndarray, q: np.ndarray, e_hat: np.ndarray,
                   n0: np.ndarray, eta: complex, material: str, thickness_m: float,
                   wavenumber_rad_m: float) -> tuple[np.ndarray, np.ndarray]:
    """20 log10 |D e| of Sionna's diffraction matrix (no spreading) for an x-polarised source
    at ``src`` seen at ``obs`` over the edge points ``q`` (edge direction ``e_hat``, ``n0`` the
    face the source sees, relative permittivity ``eta``), and the spreading factor
    ``sqrt(s' / (s (s' + s))) / s'`` that the model's field carries and Sionna applies to the
    path instead (divide it out before comparing)."""
    import drjit as dr
    import mitsuba as mi
    import sionna.rt as rt

    n = len(src)
    ki = q - src
    s_in = np.linalg.norm(ki, axis=1)
    ki = ki / s_in[:, None]
    ko = obs - q
    s_out = np.linalg.norm(ko, axis=1)
    ko = ko / s_out[:, None]
    frame = np.stack([e_hat, np.cross(n0, e_hat), n0], axis=-1)  # columns: local -> world

    def vec(v):
        v = np.broadcast_to(v @ frame, (n, 3))  # world -> local
        return mi.Vector3f(*[mi.Float(v[:, i].astype(np.float32)) for i in range(3)])

    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.dn_du, si.dn_dv = vec(e_hat), vec(-n0)
    si.dp_du = mi.Vector3f(mi.Float(s_out.astype(np.float32)), mi.Float(s_in.astype(np.float32)),
                           mi.Float(0.0))
    to_world = mi.Matrix3f([[float(frame[i, j]) for j in range(3)] for i in range(3)])
    eta_mi = mi.Complex2f(mi.Float(np.full(n, eta.real, np.float32)),
                          mi.Float(np.full(n, eta.imag, np.float32)))
    mat = rt.ITURadioMaterial("wall", material, thickness=thickness_m)
    jm = mat._diffraction_matrix(to_world, vec(ki), vec(ko), si, eta_mi,
                                 mi.Float(float(wavenumber_rad_m)))
    a4 = np.array([[np.array(jm[i][j]) for j in range(4)] for i in range(4)])
    jones = np.moveaxis(a4[:2, :2] + 1j * a4[2:, :2], -1, 0)  # Sionna's theta/phi bases
    # the x-polarised dipole's transverse field in Sionna's incident basis (theta_hat, k x theta)
    th = np.arccos(ki[:, 2])
    ph = np.arctan2(ki[:, 1], ki[:, 0])
    theta_hat = np.stack([np.cos(th) * np.cos(ph), np.cos(th) * np.sin(ph), -np.sin(th)], -1)
    e0 = np.array([1.0, 0.0, 0.0])
    jv = np.stack([theta_hat @ e0, np.cross(ki, theta_hat) @ e0], -1)
    db = 20 * np.log10(np.linalg.norm(np.einsum("nij,nj->ni", jones, jv), axis=1))
    return db, np.sqrt(s_in / (s_out * (s_in + s_out))) / s_in
