"""Scene geometry: the building as thin surfaces (pure numpy) and as a Sionna RT scene."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from diffpos.scenario import Building, Scenario
from diffpos_services.raytrace.backend import check_sionna


@dataclass(frozen=True)
class Surface:
    """One thin scene object: a union of axis-aligned rectangles with one radio material.

    Attributes
    ----------
    name : str
    material : str
        ITU-R P.2040 material name (Sionna ``itu_type``).
    thickness_m : float [m]
    rects : tuple of (axis, coord, (lo_u, hi_u), (lo_v, hi_v))
        Rectangle in the plane ``p[axis] = coord``; ``u``, ``v`` are the two other axes in
        increasing order (for axis 1, u = x and v = z) [m].
    """

    name: str
    material: str
    thickness_m: float
    rects: tuple[tuple[int, float, tuple[float, float], tuple[float, float]], ...]

    def mesh(self) -> tuple[NDArray[np.float64], NDArray[np.uint32]]:
        """Vertices ``(4 R, 3)`` [m] and triangles ``(2 R, 3)`` of the rectangles."""
        verts, faces = [], []
        for i, (axis, c, (u0, u1), (v0, v1)) in enumerate(self.rects):
            u_ax, v_ax = [a for a in range(3) if a != axis]
            quad = np.zeros((4, 3))
            quad[:, axis] = c
            quad[:, u_ax] = [u0, u1, u1, u0]
            quad[:, v_ax] = [v0, v0, v1, v1]
            verts.append(quad)
            b = 4 * i
            faces += [(b, b + 1, b + 2), (b, b + 2, b + 3)]
        return np.concatenate(verts), np.asarray(faces, dtype=np.uint32)


def building_surfaces(
    building: Building,
    anchors_m: ArrayLike,
    *,
    overlap_m: float = 0.05,
    ground_margin_m: float = 30.0,
) -> list[Surface]:
    """The scene of :func:`build_scene` as plain rectangles (see the module docstring).

    Parameters
    ----------
    building : Building
    anchors_m : array_like, shape (M, 3) [m]
        Used for the extent and height of the ground.
    overlap_m : float [m]
        How far each surface runs past the surfaces it meets.
    ground_margin_m : float [m]
        Ground extends this far beyond the anchors and the building.

    Returns
    -------
    list of Surface
    """
    b = building
    a = np.atleast_2d(np.asarray(anchors_m, dtype=np.float64))
    ov = float(overlap_m)
    x0, x1 = b.edge_x_m
    depth, top = b.depth_m, b.top_z_m
    ground_z = min(0.0, float(a[:, 2].min()) - 0.01)
    xa0, xa1 = x0 - ov, x1 + ov
    # facade: solid below the first sill, spandrels between window bands, parapet above
    lo, hi = b.window_z_m(np.arange(b.n_floors))
    bands = [(ground_z - ov, float(lo[0]))]
    bands += [(float(hi[k]), float(lo[k + 1])) for k in range(b.n_floors - 1)]
    bands.append((float(hi[-1]), top + ov))
    facade = tuple((1, 0.0, (xa0, xa1), band) for band in bands if band[1] > band[0])
    walls = (
        (0, x0, (-ov, depth + ov), (ground_z - ov, top + ov)),
        (0, x1, (-ov, depth + ov), (ground_z - ov, top + ov)),
        (1, depth, (xa0, xa1), (ground_z - ov, top + ov)),
    )
    slabs = tuple((2, float(z), (xa0, xa1), (-ov, depth + ov))
                  for z in b.floor_z_m(np.arange(b.n_floors + 1)))
    g = ground_margin_m
    ground = ((2, ground_z, (min(x0, a[:, 0].min()) - g, max(x1, a[:, 0].max()) + g),
               (float(a[:, 1].min()) - g, depth + ov)),)
    out = [
        Surface("facade", b.wall_material, b.wall_thickness_m, facade),
        Surface("walls", b.wall_material, b.wall_thickness_m, walls),
        Surface("slabs", b.slab_material, b.slab_thickness_m, slabs),
        Surface("ground", b.ground_material, 0.5, ground),
    ]
    z_span = (float(b.first_floor_z_m) - ov, top + ov)
    for i, p in enumerate(b.partitions):
        span = (p.span_m[0] - ov, p.span_m[1] + ov)
        rect = (0, p.position_m, span, z_span) if p.axis == "x" else (1, p.position_m, span,
                                                                       z_span)
        out.append(Surface(f"partition{i}", p.material, p.thickness_m, (rect,)))
    return out


def build_scene(scenario: Scenario, *, overlap_m: float = 0.05) -> Any:
    """The scenario's building as a ``sionna.rt.Scene`` (requires the optional extra).

    Returns
    -------
    sionna.rt.Scene
        With the carrier frequency, the dipole transmit array and the dual-polarised
        isotropic receive array set; no transmitters or receivers yet.

    Raises
    ------
    RaytraceUnavailable
        If Sionna RT cannot be imported.
    ValueError
        If a material is undefined at the carrier (Sionna's ITU table).
    """
    check_sionna()
    # sionna/mitsuba are the optional extra: imported here, never at module level
    import mitsuba as mi
    import sionna.rt as rt

    b, r = scenario.building, scenario.radio
    scene = rt.load_scene()
    scene.frequency = float(r.frequency_hz)
    scene.bandwidth = float(r.bandwidth_hz)
    materials: dict[tuple[str, float], Any] = {}
    objects = []
    for s in building_surfaces(b, scenario.anchor_positions_m(), overlap_m=overlap_m):
        key = (s.material, float(s.thickness_m))
        if key not in materials:
            materials[key] = rt.ITURadioMaterial(f"{s.material}-{len(materials)}", s.material,
                                                 thickness=float(s.thickness_m))
        v, f = s.mesh()
        mesh = mi.Mesh(s.name, len(v), len(f), has_vertex_normals=False,
                       has_vertex_texcoords=False)
        params = mi.traverse(mesh)
        params["vertex_positions"] = mi.Float(v.astype(np.float32).ravel())
        params["faces"] = mi.UInt32(f.ravel())
        params.update()
        objects.append(rt.SceneObject(mi_mesh=mesh, name=s.name, radio_material=materials[key]))
    try:
        scene.edit(add=objects)
    except Exception as exc:
        raise ValueError(f"Sionna could not build the scene at {r.frequency_hz / 1e9:g} GHz: "
                         f"{exc} (check the building's materials)") from None
    scene.tx_array = rt.PlanarArray(num_rows=1, num_cols=1, pattern="dipole", polarization="V")
    scene.rx_array = rt.PlanarArray(num_rows=1, num_cols=1, pattern="iso", polarization="VH")
    return scene
