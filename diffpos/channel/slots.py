"""The numpy O2I channel emulator's building blocks: materials, geometry helpers and the slot
builders of :func:`diffpos.channel.emulator.emulate_channel` (direct, reflections, UTD diffraction,
their combinations) -- the reference the compiled kernels are tested against.

:mod:`diffpos.channel.emulator` keeps the result types, the detector and the public API; the
model is described in that module's docstring.

Window edges. The UTD field of a window edge is the half-plane's: the facade wall above the
window (upper edge), below it (lower edge), the side wall running into the building
(vertical edges). At ``radio.channel_max_order`` 2 (the paper's 18 mechanisms, the default
channel) the horizontal edges' half-plane is a perfect conductor, as in the paper. Every
family beyond the 18 (orders >= 3), the vertical edges, and at orders >= 3 also the 18's
horizontal edges, see a dielectric sheet of the walls' material instead (ITU-R P.2040;
Luebbers' finite-conductivity UTD, ``gtd_halfplane``'s "Dielectric sheet"): one material model
for every edge, as the ray tracer's wedge (Sionna RT weights the reflection terms of its UTD
by the faces' material coefficients). The conductor's reflection terms keep the field behind
the sheet too strong deep in its shadow (the image nodes of the edge + slab-series families).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from diffpos.channel.gtd_halfplane import _fresnel, diffracted_field, wavenumber_rad_m
from diffpos.channel.linkbudget import snr_db
from diffpos.constants import SPEED_OF_LIGHT_M_S
from diffpos.paths.mechanisms import Recipe
from diffpos.paths.model import FloorFrame, diffracted_path, direct_opening, specular_path
from diffpos.scenario import ITU_MATERIALS, Building, Radio

FloatArray = NDArray[np.float64]
_C = SPEED_OF_LIGHT_M_S

# --------------------------------------------------------------------------------------------
# materials
# --------------------------------------------------------------------------------------------


def itu_permittivity(material: str, frequency_hz: float) -> complex:
    """Complex relative permittivity ``eta' - j 17.98 sigma / f_GHz`` (ITU-R P.2040-1).

    Parameters
    ----------
    material : str
        Name in :data:`diffpos.scenario.ITU_MATERIALS`.
    frequency_hz : float [Hz]

    Returns
    -------
    complex [-]
        E.g. concrete at 28 GHz: ``5.24 - 0.402j``.
    """
    a, b, c, d, _lo, _hi = ITU_MATERIALS[material]
    f = frequency_hz / 1e9
    return complex(a * f**b, -17.98 * c * f**d / f)


def slab_loss_db(material: str, thickness_m: float, frequency_hz: float) -> float:
    """Normal-incidence transmission loss of a slab: bulk attenuation + two interfaces [dB].

    ``8.686 * Im(-k0 sqrt(eta)) * d - 2 * 10 log10(1 - |Gamma_0|^2)`` with the normal-incidence
    Fresnel coefficient ``Gamma_0 = (1 - sqrt(eta)) / (1 + sqrt(eta))``; multiple internal
    reflections are neglected (thick, lossy slabs). Concrete, 0.2 m, 28 GHz: about 90 dB;
    plasterboard, 25 mm: about 6 dB.
    """
    eta = itu_permittivity(material, frequency_hz)
    n = np.sqrt(eta)  # principal root: Im(n) <= 0 for eta'' <= 0
    k0 = float(wavenumber_rad_m(frequency_hz))
    alpha_np_m = -k0 * n.imag
    g0 = (1 - n) / (1 + n)
    return float(8.685889638 * alpha_np_m * thickness_m - 2 * 10 * np.log10(1 - abs(g0) ** 2))


def fresnel_coefficients(cos_theta: ArrayLike, eta: complex) -> tuple[NDArray, NDArray]:
    """Fresnel reflection coefficients of a half-space (TE/s and TM/p).

    Parameters
    ----------
    cos_theta : array_like [-]
        Cosine of the incidence angle from the surface normal (in [0, 1]).
    eta : complex
        Relative permittivity of the half-space.

    Returns
    -------
    gamma_s, gamma_p : ndarray of complex
        ``(cos - sqrt(eta - sin^2)) / (cos + sqrt(eta - sin^2))`` and
        ``(eta cos - sqrt(eta - sin^2)) / (eta cos + sqrt(eta - sin^2))``.
    """
    return _fresnel(np.asarray(cos_theta, dtype=np.float64), eta)

# --------------------------------------------------------------------------------------------
# geometry helpers
# --------------------------------------------------------------------------------------------


def _unit(v: FloatArray) -> tuple[FloatArray, FloatArray]:
    n = np.sqrt(np.einsum("...i,...i->...", v, v))
    with np.errstate(invalid="ignore", divide="ignore"):
        return v / n[..., None], n


def _field_norm(e: NDArray) -> FloatArray:
    """Magnitude ``sqrt(e . conj(e))`` of complex field vectors ``(..., 3)``."""
    return np.sqrt(np.einsum("...i,...i->...", e, e.conj()).real)


def _cross(a: NDArray, b: NDArray) -> NDArray:
    """``np.cross`` over the last axis (of length 3), without its axis bookkeeping."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack(np.broadcast_arrays(a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0),
                    axis=-1)


def _zenith_deg(d: FloatArray) -> FloatArray:
    u, _ = _unit(d)
    return np.degrees(np.arccos(np.clip(u[..., 2], -1.0, 1.0)))


def _pattern_db(zenith_deg: FloatArray, hpbw_deg: float | None, peak_deg: float) -> FloatArray:
    if hpbw_deg is None:
        return np.zeros_like(zenith_deg)
    return -np.minimum(12.0 * ((zenith_deg - peak_deg) / hpbw_deg) ** 2, 30.0)


def _mirror(p: FloatArray, axis: int, c: FloatArray | float) -> FloatArray:
    q = p.copy()
    q[..., axis] = 2.0 * c - p[..., axis]
    return q


def _transverse(e: FloatArray, d: FloatArray) -> NDArray[np.complex128]:
    """Field of a short dipole ``e`` radiating along unit ``d``: ``e - (e.d) d``."""
    return (e - np.einsum("...i,...i->...", e, d)[..., None] * d).astype(np.complex128)


def _reflect_field(E: NDArray, k_in: FloatArray, axis: int, eta: complex) -> NDArray:
    """Reflect the field vector ``E`` of a ray with unit direction ``k_in`` off the plane
    normal to ``axis`` (Fresnel TE/TM split). Returns the reflected field vector."""
    nrm = np.zeros(3)
    nrm[axis] = 1.0
    cos_t = np.abs(k_in[..., axis])
    k_out = k_in.copy()
    k_out[..., axis] = -k_in[..., axis]
    s = _cross(k_in, nrm)
    s, sn = _unit(s)
    # normal incidence: any transverse direction works as s
    fallback = np.zeros(3)
    fallback[(axis + 1) % 3] = 1.0
    s = np.where((sn > 1e-12)[..., None], s, fallback)
    p_in = _cross(s, k_in)
    p_out = _cross(s, k_out)
    gs, gp = fresnel_coefficients(cos_t, eta)
    es = np.einsum("...i,...i->...", E, s)
    ep = np.einsum("...i,...i->...", E, p_in)
    return (gs * es)[..., None] * s + (gp * ep)[..., None] * p_out


def _materials(b: Building, frequency_hz: float) -> tuple:
    """``(eta_ground, eta_in, wall_db, slab_db, glass_db, parts)`` of a building at a carrier:
    the permittivities of the ground and of the interior surfaces, the wall / slab / glass
    losses [dB] and the partitions as ``(axis 0|1, position_m, span_m, loss_db)``."""
    f = frequency_hz
    wall_db = (b.wall_loss_db if b.wall_loss_db is not None
               else slab_loss_db(b.wall_material, b.wall_thickness_m, f))
    slab_db = (b.slab_loss_db if b.slab_loss_db is not None
               else slab_loss_db(b.slab_material, b.slab_thickness_m, f))
    parts = [
        (0 if p.axis == "x" else 1, p.position_m, p.span_m,
         p.loss_db if p.loss_db is not None else slab_loss_db(p.material, p.thickness_m, f))
        for p in b.partitions
    ]
    return (itu_permittivity(b.ground_material, f), itu_permittivity(b.interior_material, f),
            wall_db, slab_db, b.glass_loss_db if b.windows == "glass" else 0.0, parts)


def partition_permittivities(b: Building, frequency_hz: float) -> list[complex]:
    """The relative permittivity of every partition's material (ITU-R P.2040) at a carrier:
    a partition reflection's Fresnel coefficients (its loss on crossing is ``_materials``'s)."""
    return [itu_permittivity(p.material, frequency_hz) for p in b.partitions]


class _Ctx:
    """Per-call constants shared by the slot builders."""

    def __init__(self, building: Building, radio: Radio, nodes: FloatArray, anchors: FloatArray):
        b, r = building, radio
        self.b, self.r = b, r
        self.f = r.frequency_hz
        self.k = float(wavenumber_rad_m(self.f))
        self.lam = r.wavelength_m
        self.e0 = np.asarray(r.polarization, dtype=np.float64)
        self.node = nodes[:, None, :]  # (N,1,3)
        # (1,M,3) shared anchors, or (N,M,3) per-node anchors (pair_snr_db)
        self.anchor = anchors[None, :, :] if anchors.ndim == 2 else anchors
        self.shape = (nodes.shape[0], self.anchor.shape[1])
        floor = b.floor_index(nodes[:, 2])
        self.floor = floor
        self.z_floor = b.floor_z_m(floor)[:, None]  # (N,1)
        self.z_ceil = self.z_floor + b.floor_height_m
        # the node floor's planes, shared with the path model (diffpos.paths.model)
        self.frame = FloorFrame.from_building(b, floor[:, None])
        self.x0, self.x1 = self.frame.x0, self.frame.x1
        (self.eta_ground, self.eta_in, self.wall_db, self.slab_db, self.glass_db,
         self.parts) = _materials(b, self.f)
        self.eta_parts = partition_permittivities(b, self.f)
        self.eta_wall = itu_permittivity(b.wall_material, self.f)  # the edges' sheet

    def edge_permittivity(self, edge: str) -> complex | None:
        """The sheet of one of the 18 slots' window edges (module docstring, "Window edges"):
        the walls' material (``gtd_halfplane``'s "Dielectric sheet") at a vertical edge and,
        at ``channel_max_order`` >= 3, at the horizontal ones; a perfect conductor (None) at
        the horizontal edges at order 2 (the paper's physics). The families beyond the 18
        always see the walls' material (:func:`family_slot`)."""
        if edge.startswith("vertical") or self.r.channel_max_order >= 3:
            return self.eta_wall
        return None

    def partition_loss_db(self, p: FloatArray, q: FloatArray) -> FloatArray:
        """Total loss of the partitions crossed by segments ``p -> q`` (inside) [dB]."""
        loss = np.zeros(np.broadcast_shapes(p.shape, q.shape)[:-1])
        for axis, pos, (lo, hi), db in self.parts:
            a, bq = p[..., axis] - pos, q[..., axis] - pos
            cross = a * bq < 0
            other = 1 - axis
            with np.errstate(invalid="ignore", divide="ignore"):
                t = a / (a - bq)
                o = p[..., other] + t * (q[..., other] - p[..., other])
            loss = loss + np.where(cross & (o > lo) & (o < hi), db, 0.0)
        return loss

    def tx_field(self, d_unit: FloatArray) -> NDArray[np.complex128]:
        """Dipole field (with antenna pattern amplitude) leaving the anchor along ``d_unit``."""
        g_db = _pattern_db(_zenith_deg(d_unit), self.r.tx_hpbw_deg, self.r.tx_peak_deg)
        return _transverse(self.e0, d_unit) * (10 ** (g_db / 20))[..., None]

    def ray_gain(self, amp: FloatArray, length_m: FloatArray, loss_db: FloatArray) -> NDArray:
        """Complex gain of a ray of unfolded length ``length_m``: field magnitude ``amp``, Friis
        spreading ``lambda / (4 pi d)``, penetration loss and the phase ``exp(-j k d)``."""
        return (amp * (self.lam / (4 * np.pi * length_m)) * 10 ** (-loss_db / 20)
                * np.exp(-1j * self.k * length_m))

# --------------------------------------------------------------------------------------------
# slot builders: each returns (length_m, gain, aod_deg, aoa_deg, valid), shapes (N, M)
# --------------------------------------------------------------------------------------------


def _direct(c: _Ctx):
    a, n = c.anchor, c.node
    d = n - a
    u, length = _unit(d)
    t = -a[..., 1] / d[..., 1]  # facade crossing (anchor y < 0 < node y)
    xc, zc, through_window = direct_opening(a, n, c.frame)
    # slabs crossed between the facade crossing and the node
    b = c.b
    k_cross = b.floor_index(zc)
    k_node = c.floor[:, None]
    n_slabs = np.abs(k_node - k_cross)  # k_cross = -1 below the first floor (its slab too)
    # crossing another floor's window band (no wall) or a wall
    zlo_c, zhi_c = b.window_z_m(k_cross)
    other_window = ((k_cross >= 0) & (k_cross < b.n_floors) & (zc > zlo_c) & (zc < zhi_c)
                    & (xc > c.x0) & (xc < c.x1))
    loss = np.where(through_window | other_window, c.glass_db, c.wall_db) + n_slabs * c.slab_db
    entry = a + t[..., None] * d
    loss = loss + c.partition_loss_db(entry, n)
    E = c.tx_field(u)
    amp = _field_norm(E)
    gain = c.ray_gain(amp, length, loss)
    valid = np.ones(c.shape, dtype=bool)
    return length, gain, _zenith_deg(u), _zenith_deg(-u), valid


def _reflections(c: _Ctx, planes: list[str], *, ground: bool = False):
    """Specular path anchor [-> ground] -> window -> planes... -> node (image method; the
    geometry is :func:`diffpos.paths.model.specular_path`, shared with the path model)."""
    a = np.broadcast_to(c.anchor, (*c.shape, 3)).copy()
    n = np.broadcast_to(c.node, (*c.shape, 3)).copy()
    g = specular_path(a, n, c.frame, planes, ground=ground)
    length, valid, pts = g.length_m, g.valid.copy(), g.points
    # field: departure, ground bounce, then inside bounces
    first_target = pts[0] if not ground else g.ground_point
    u0, _ = _unit(first_target - a)
    E = c.tx_field(u0)
    loss = np.full(c.shape, c.glass_db)
    if ground:
        gpt = first_target
        k_in = u0
        E = _reflect_field(E, k_in, 2, c.eta_ground)
        u_enter, _ = _unit(pts[0] - gpt)
    else:
        u_enter = u0
    k_in = u_enter
    for j in range(len(planes)):
        E = _reflect_any(E, k_in, *_bounce(c, planes, g, j))
        loss = loss + c.partition_loss_db(pts[j], pts[j + 1])
        k_in, _ = _unit(pts[j + 2] - pts[j + 1])
    loss = loss + c.partition_loss_db(pts[-2], pts[-1])
    amp = _field_norm(E)
    gain = c.ray_gain(amp, length, loss)
    aoa = _zenith_deg(pts[-2] - n)
    valid &= np.isfinite(length) & np.isfinite(amp)
    return length, np.where(valid, gain, 0), _zenith_deg(u0), aoa, valid


def _edge_frame(edge: str) -> tuple[FloatArray, FloatArray]:
    """Edge tangent ``e`` and half-plane face ``t0`` of a window edge (``diffracted_field``'s
    ``edge_dir``, ``face_dir``): the upper edge's half-plane is the wall above the window (``e
    = +x, t0 = +z``), the lower edge's the wall below it (``-x, -z``); a vertical edge's at
    a facade end (``"vertical x1"`` at ``x0``, ``"vertical x2"`` at ``x1``) is the side wall,
    running into the building (``t0 = +y``; ``e = +z`` / ``-z``, so ``n0 = e x t0`` points
    out of the building: ``-x`` / ``+x``)."""
    if edge == "upper":
        return np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0])
    if edge == "lower":
        return np.array([-1.0, 0.0, 0.0]), np.array([0.0, 0.0, -1.0])
    sense = 1.0 if edge == "vertical x1" else -1.0
    return np.array([0.0, 0.0, sense]), np.array([0.0, 1.0, 0.0])


def _diffracted(c: _Ctx, edge: str, then: str | None = None, *, sheet: complex | None = None,
                field=None):
    """Anchor -> window edge (UTD) [-> one inside reflection] -> node (geometry:
    :func:`diffpos.paths.model.diffracted_path`, shared with the path model; corner diffraction is
    dropped in both). ``sheet``: the edge's half-plane (None: a perfect conductor, else its
    permittivity; :meth:`_Ctx.edge_permittivity` for the 18). ``field``: instead a function
    ``(c, a, obs, q, e_dir, face) -> E``, the edge's field at ``obs``
    (:func:`diffpos.channel.edge_snr.edge_slots_snr_db` passes Sionna RT's window edge)."""
    a = np.broadcast_to(c.anchor, (*c.shape, 3))
    n = np.broadcast_to(c.node, (*c.shape, 3))
    g = diffracted_path(a, n, c.frame, edge, then)
    q = g.points[0]
    valid = g.valid.copy()
    obs = n
    if then is not None:
        axis, coord = c.frame.plane(then)
        obs = _mirror(np.array(n), axis, np.broadcast_to(coord, c.shape))
    e_dir, face = _edge_frame(edge)
    if field is not None:
        E = field(c, a, obs, q, e_dir, face)
    else:
        E = diffracted_field(a, obs, q, e_dir, face, c.e0, frequency_hz=c.f,
                             coefficients="utd", spreading="spherical", face_permittivity=sheet)
    # antenna pattern on departure
    g_db = _pattern_db(_zenith_deg(q - a), c.r.tx_hpbw_deg, c.r.tx_peak_deg)
    E = E * (10 ** (g_db / 20))[..., None]
    pts_last = q
    loss = np.zeros(c.shape)  # the diffracted ray passes the edge, not the glass
    if then is None:
        loss = loss + c.partition_loss_db(q, n)
    else:
        d = obs - q
        rp = g.points[1]
        k_in, _ = _unit(d)
        E = _reflect_field(E, k_in, axis, c.eta_in)
        loss = loss + c.partition_loss_db(q, rp) + c.partition_loss_db(rp, n)
        pts_last = rp
    length = g.length_m
    amp_vec = E * (c.lam / (4 * np.pi)) * 10 ** (-loss / 20)[..., None]
    amp = _field_norm(amp_vec)
    gain = amp * np.exp(-1j * c.k * length)
    valid &= np.isfinite(amp)
    return (length, np.where(valid, gain, 0), _zenith_deg(q - a), _zenith_deg(pts_last - n),
            valid)


def _diffracted_family(c: _Ctx, rec: Recipe):
    """Anchor [-> ground] -> window edge (UTD) -> the recipe's inside reflections -> node: a
    family of :func:`diffpos.paths.mechanisms.mechanism_set` beyond the 18 (geometry:
    :func:`diffpos.paths.model.diffracted_path`). The ground bounce is the Fresnel reflection
    of the dipole field on the ground (the image source's field then meets the edge); each
    inside reflection is the Fresnel reflection of the diffracted field at its point, in path
    order; every inside segment adds its partitions' loss. The edge is a dielectric sheet of
    the walls' material (module docstring, "Window edges")."""
    a = np.broadcast_to(c.anchor, (*c.shape, 3))
    n = np.broadcast_to(c.node, (*c.shape, 3))
    g = diffracted_path(a, n, c.frame, rec.edge, rec.planes, ground=rec.ground)
    q, pts = g.points[0], g.points
    obs = _image(c, n, rec.planes, g)
    e_dir, face = _edge_frame(rec.edge)
    if rec.ground:
        src = _mirror(np.array(a), 2, 0.0)
        u0, _ = _unit(g.ground_point - a)
        e_src = _reflect_field(c.tx_field(u0), u0, 2, c.eta_ground)  # pattern included
        aod = _zenith_deg(u0)
    else:
        src = a
        g_db = _pattern_db(_zenith_deg(q - a), c.r.tx_hpbw_deg, c.r.tx_peak_deg)
        e_src = c.e0 * (10 ** (g_db / 20))[..., None]
        aod = _zenith_deg(q - a)
    with np.errstate(invalid="ignore", divide="ignore"):
        E = diffracted_field(src, obs, q, e_dir, face, e_src, frequency_hz=c.f,
                             coefficients="utd", spreading="spherical",
                             face_permittivity=c.eta_wall)
        loss = np.zeros(c.shape)  # the diffracted ray passes the edge, not the glass
        for j in range(len(rec.planes)):
            k_in, _ = _unit(pts[j + 1] - pts[j])
            E = _reflect_any(E, k_in, *_bounce(c, rec.planes, g, j))
        for j in range(len(pts) - 1):
            loss = loss + c.partition_loss_db(pts[j], pts[j + 1])
        amp = _field_norm(E * (c.lam / (4 * np.pi)) * 10 ** (-loss / 20)[..., None])
    length = g.length_m
    valid = g.valid & np.isfinite(amp)
    gain = amp * np.exp(-1j * c.k * length)
    return length, np.where(valid, gain, 0), aod, _zenith_deg(pts[-2] - n), valid


def _bounce(c: _Ctx, planes, g, j: int):
    """(axis, permittivity) of the ``j``-th reflection in path order of a path ``g``
    (``specular_path`` / ``diffracted_path``) through ``planes``: a slab or wall (the interior
    material), or, in a partition family (``g.order``), per pair the partition's."""
    if g.order is None:
        return c.frame.plane(planes[j])[0], c.eta_in
    is_p = g.order[..., j] == list(planes).index("partition")
    pax = np.array([r[0] for r in c.frame.partitions])[g.partition]
    eta_p = np.asarray(c.eta_parts, dtype=np.complex128)[g.partition]
    return np.where(is_p, pax, 2), np.where(is_p, eta_p, c.eta_in)


def _reflect_any(E: NDArray, k_in: FloatArray, axis, eta) -> NDArray:
    """:func:`_reflect_field` with a per-pair axis (an array) too."""
    if np.ndim(axis) == 0:
        return _reflect_field(E, k_in, int(axis), eta)
    out = np.zeros_like(E)
    for ax in np.unique(axis):
        out = np.where((axis == ax)[..., None], _reflect_field(E, k_in, int(ax), eta), out)
    return out


def _image(c: _Ctx, n: FloatArray, planes, g) -> FloatArray:
    """The node imaged in every plane (a partition family: per pair its partition)."""
    obs = np.array(n)
    for p in reversed(planes):
        if p == "partition":
            rows = np.array([r[:2] for r in c.frame.partitions])[g.partition]
            ax, pos = rows[..., 0].astype(int), rows[..., 1]
            for a in (0, 1):
                obs[..., a] = np.where(ax == a, 2.0 * pos - obs[..., a], obs[..., a])
            continue
        axis, coord = c.frame.plane(p)
        obs = _mirror(obs, axis, np.broadcast_to(coord, c.shape))
    return obs


def family_slot(c: _Ctx, rec: Recipe):
    """One slot of any :class:`diffpos.paths.mechanisms.Recipe` (the 18 and the higher-order
    families of :func:`diffpos.paths.mechanisms.mechanism_set`): length, gain, aod, aoa,
    valid (N, M). The 18 keep their own builders (:func:`_slots`); this serves the rest (every
    window edge a dielectric sheet of the walls' material: module docstring). A
    partition family reflects on the partition of the shortest existing path (its material's
    Fresnel coefficients); none exists without partitions."""
    if "partition" in rec.planes and not c.frame.partitions:
        nan = np.full(c.shape, np.nan)
        return nan, np.zeros(c.shape, dtype=np.complex128), nan, nan, np.zeros(c.shape, bool)
    if rec.kind == "direct":
        return _direct(c)
    if rec.kind == "spec":
        return _reflections(c, list(rec.planes), ground=rec.ground)
    if not rec.planes and not rec.ground:
        return _diffracted(c, rec.edge, sheet=c.eta_wall)
    if len(rec.planes) == 1 and not rec.ground and rec.planes[0] != "partition":
        return _diffracted(c, rec.edge, rec.planes[0], sheet=c.eta_wall)
    return _diffracted_family(c, rec)


def _slots(c: _Ctx, radio: Radio, extra: tuple[Recipe, ...] = ()):
    """Every slot of every pair: length, gain, aod, aoa, valid, power, snr (N, M, K): the 18
    of :data:`diffpos.paths.mechanisms.MECHANISMS`, then the ``extra`` recipes (the families
    :func:`diffpos.paths.mechanisms.mechanism_set` adds after them)."""
    up, low = c.edge_permittivity("upper"), c.edge_permittivity("lower")
    results = [
        _direct(c),
        _reflections(c, [], ground=True),
        _reflections(c, ["floor"]),
        _reflections(c, ["ceiling"]),
        _reflections(c, ["back"]),
        _reflections(c, ["side x1"]),
        _reflections(c, ["side x2"]),
        _diffracted(c, "upper", sheet=up),
        _diffracted(c, "lower", sheet=low),
        _diffracted(c, "upper", "floor", sheet=up),
        _diffracted(c, "upper", "ceiling", sheet=up),
        _diffracted(c, "lower", "floor", sheet=low),
        _diffracted(c, "lower", "ceiling", sheet=low),
        _diffracted(c, "upper", "back", sheet=up),
        _reflections(c, ["ceiling"], ground=True),
        _reflections(c, ["ceiling", "floor"]),
        _reflections(c, ["floor", "ceiling"]),
        _reflections(c, ["ceiling", "back"]),
    ]
    results += [family_slot(c, rec) for rec in extra]
    length = np.stack([r[0] for r in results], axis=-1)
    gain = np.stack([r[1] for r in results], axis=-1).astype(np.complex128)
    aod = np.stack([r[2] for r in results], axis=-1)
    aoa = np.stack([r[3] for r in results], axis=-1)
    valid = np.stack([r[4] for r in results], axis=-1) & np.isfinite(length)
    gain = np.where(valid, gain, 0)
    length = np.where(valid, length, np.nan)
    power, snr = _power_snr(gain, aoa, valid, radio)
    return length, gain, aod, aoa, valid, power, snr


def _power_snr(gain: NDArray, aoa: FloatArray, valid: NDArray, radio: Radio
               ) -> tuple[FloatArray, FloatArray]:
    """Received power [dBm] and SNR [dB] of slots' complex gains (receive pattern at the
    arrival zenith ``aoa``); -inf where not ``valid``."""
    rx_db = _pattern_db(aoa, radio.rx_hpbw_deg, radio.rx_peak_deg)
    with np.errstate(divide="ignore"):
        power = (radio.tx_power_dbm + radio.tx_gain_dbi + radio.rx_gain_dbi + rx_db
                 + 20 * np.log10(np.abs(gain)))
    snr = snr_db(power, bandwidth_hz=radio.bandwidth_hz,
                 processing_gain_db=radio.processing_gain_db,
                 temperature_k=radio.noise_temperature_k, noise_figure_db=radio.noise_figure_db)
    return np.where(valid, power, -np.inf), np.where(valid, snr, -np.inf)
