"""Corrections to the installed Sionna RT, applied when the ray tracer is loaded.

Sionna RT 2.2.0: the distances of a diffracted path (``s'``, source to edge, and ``s``, edge to
target, which set the diffraction's spreading factor ``sqrt(s' / (s (s + s')))`` and the
distance parameter of its transition function) are summed over the path's vertices depth by
depth up to ``max_depth``. The first empty depth of a path with fewer interactions than
``max_depth`` still adds a segment to the vertex stored there (an unused slot) and the last
segment is then measured from that slot. The same diffracted path therefore gets a different
gain at another ``max_depth``: on the paper building a window-edge diffraction followed by a
partition crossing (``Tx-D-T-Rx``) came out 2.4-6.0 dB weaker at depth 4 than at depth 2 (12
receivers; median 3.4 dB), while its traced length and vertices were the same. Found by the
channel-mix study (docs/channel_mix.md, session 19); not fixed upstream in the pinned version.

:func:`apply_corrections` replaces that one method by :func:`_diffraction_distances`, which
stops at a path's first empty depth. The corrections applied are recorded with the versions of
every trace (dataset metadata, live trace files) and are part of the live cache key, so a trace
made without them is never reused.
"""

from __future__ import annotations

from typing import Any

__all__ = ["CORRECTIONS", "apply_corrections"]

#: The corrections this module makes, per Sionna RT version it makes them for.
CORRECTIONS: dict[str, tuple[str, ...]] = {
    "2.2.0": ("diffraction-distances-stop-at-path-end",),
}


def _diffraction_distances(self: Any, paths: Any, src_positions: Any,
                           tgt_positions: Any) -> tuple[Any, Any]:
    """``(s, s')`` of every path of ``paths``: the lengths after and before its diffraction,
    over the path's own vertices only (source, its interactions, target)."""
    import drjit as dr
    import mitsuba as mi
    from sionna.rt.constants import InteractionType

    n = paths.buffer_size
    s = dr.zeros(mi.Float, n)
    s_prime = dr.zeros(mi.Float, n)
    inside = dr.full(mi.Bool, True, n)  # the depth is one of the path's interactions
    after = dr.full(mi.Bool, False, n)  # a diffraction came before this depth
    prev = dr.copy(src_positions)
    for depth in range(1, int(paths.max_depth) + 1):
        d = dr.full(mi.UInt, depth, n)
        kind = paths.get_interaction_type(d, inside)
        inside &= kind != InteractionType.NONE
        vertex = paths.get_vertex(d, inside)
        seg = dr.norm(vertex - prev)
        s = dr.select(inside & after, s + seg, s)
        s_prime = dr.select(inside & ~after, s_prime + seg, s_prime)
        after |= inside & (kind == InteractionType.DIFFRACTION)
        prev = dr.select(inside, vertex, prev)
    last = dr.norm(tgt_positions - prev)
    return dr.select(after, s + last, s), dr.select(after, s_prime, s_prime + last)


def apply_corrections(sionna_version: str) -> tuple[str, ...]:
    """Apply the corrections known for ``sionna_version`` (idempotent); returns their names."""
    names = CORRECTIONS.get(sionna_version, ())
    if "diffraction-distances-stop-at-path-end" in names:
        from sionna.rt.path_solvers.field_calculator import FieldCalculator

        FieldCalculator._diffraction_compute_s_s_prime = _diffraction_distances
    return names
