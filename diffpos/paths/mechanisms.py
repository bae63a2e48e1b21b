"""The first-arrival mechanisms of the path model: their labels, recipes and slot sets.

Plain data, importable without the compiled kernels (the tracker's and the fusion's settings
types use it, and ``diffpos VERB --help`` must not load numba); :mod:`diffpos.paths.model`
evaluates the mechanisms and :mod:`diffpos.paths.model_nb` holds their compiled twin (a test
checks the tables agree).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

#: Slot labels, in slot order (shared with :data:`diffpos.channel.emulator.MECHANISMS`).
MECHANISMS: tuple[str, ...] = (
    "Tx-Rx",
    "Tx-R(ground)-Rx",
    "Tx-R(floor)-Rx",
    "Tx-R(ceiling)-Rx",
    "Tx-R(back)-Rx",
    "Tx-R(side x1)-Rx",
    "Tx-R(side x2)-Rx",
    "Tx-D(upper)-Rx",
    "Tx-D(lower)-Rx",
    "Tx-D(upper)-R(floor)-Rx",
    "Tx-D(upper)-R(ceiling)-Rx",
    "Tx-D(lower)-R(floor)-Rx",
    "Tx-D(lower)-R(ceiling)-Rx",
    "Tx-D(upper)-R(back)-Rx",
    "Tx-R(ground)-R(ceiling)-Rx",
    "Tx-R(ceiling)-R(floor)-Rx",
    "Tx-R(floor)-R(ceiling)-Rx",
    "Tx-R(ceiling)-R(back)-Rx",
)

class Recipe(NamedTuple):
    """How a mechanism's path runs: ``kind`` ``"direct"``, ``"spec"`` (specular reflections
    entering through the window) or ``"diff"`` (diffraction on a window edge); ``ground``: a
    ground bounce outside first; ``edge``: ``"upper"`` / ``"lower"`` window edge, or
    ``"vertical x1"`` / ``"vertical x2"``: the window's vertical edge at the facade end
    ``x = x0`` / ``x1`` (``"diff"`` only, else None); ``planes``: the inside reflections in
    path order (``"floor"``, ``"ceiling"``, ``"back"``, ``"side x1"``, ``"side x2"``), or
    ``"partition"`` (last, at most once, with slab reflections only): a reflection on one of
    the building's interior partitions, wherever the ray meets it among the slab reflections
    (a vertical mirror commutes with the horizontal ones: the length does not depend on the
    place, the geometry decides it), on the partition giving the shortest existing path."""

    kind: str
    ground: bool = False
    edge: str | None = None
    planes: tuple[str, ...] = ()

    @property
    def order(self) -> int:
        """Interactions of the path: the ground bounce, the diffraction, the reflections."""
        return int(self.ground) + int(self.kind == "diff") + len(self.planes)

    @property
    def label(self) -> str:
        """The mechanism's label (``Tx-R(ground)-D(lower)-R(ceiling)-Rx``)."""
        toks = ["R(ground)"] if self.ground else []
        if self.kind == "diff":
            toks.append(f"D({self.edge})")
        toks += [f"R({p})" for p in self.planes]
        return "-".join(["Tx", *toks, "Rx"])


#: The recipe of every slot of :data:`MECHANISMS`.
RECIPES: tuple[Recipe, ...] = (
    Recipe("direct"),
    Recipe("spec", True),
    Recipe("spec", planes=("floor",)),
    Recipe("spec", planes=("ceiling",)),
    Recipe("spec", planes=("back",)),
    Recipe("spec", planes=("side x1",)),
    Recipe("spec", planes=("side x2",)),
    Recipe("diff", edge="upper"),
    Recipe("diff", edge="lower"),
    Recipe("diff", edge="upper", planes=("floor",)),
    Recipe("diff", edge="upper", planes=("ceiling",)),
    Recipe("diff", edge="lower", planes=("floor",)),
    Recipe("diff", edge="lower", planes=("ceiling",)),
    Recipe("diff", edge="upper", planes=("back",)),
    Recipe("spec", True, planes=("ceiling",)),
    Recipe("spec", planes=("ceiling", "floor")),
    Recipe("spec", planes=("floor", "ceiling")),
    Recipe("spec", planes=("ceiling", "back")),
)
#: Slots whose last leg is a specular ray entering through the opening (incl. the direct one).
SPECULAR_SLOTS: tuple[int, ...] = (0, 1, 2, 3, 4, 5, 6, 14, 15, 16, 17)
#: Slots with a window-edge diffraction.
DIFFRACTION_SLOTS: tuple[int, ...] = (7, 8, 9, 10, 11, 12, 13)
_AXIS = {"floor": 2, "ceiling": 2, "back": 1, "side x1": 0, "side x2": 0, "ground": 2}
#: The order of :data:`MECHANISMS` (every mechanism has at most 2 interactions); the default
#: of :func:`mechanism_set`.
DEFAULT_ORDER = 2
#: Walls that reflect once (at the end of a path) in the families of :func:`mechanism_set`.
WALLS: tuple[str, ...] = ("back", "side x1", "side x2")
#: The window's vertical edges (at the facade ends ``x = x0`` / ``x1``, from the sill to the
#: lintel of the node's floor): their families (order > 2) take only slab reflections after
#: the edge (Sionna's vertical-edge first arrivals, docs/channel_mix.md).
VERTICAL_EDGES: tuple[str, ...] = ("vertical x1", "vertical x2")
#: A wall reflection ends a family only after at most this many slab reflections (each wall
#: triples the families; Sionna's first arrivals with a wall had <= 1 slab reflection before
#: it, docs/raytrace.md).
WALL_AFTER_SLABS = 1


@dataclass(frozen=True)
class MechanismSet:
    """A list of mechanisms: the 18 of :data:`MECHANISMS` first (same slots, labels and
    recipes), then the families :func:`mechanism_set` adds up to ``max_order``.

    Attributes
    ----------
    max_order : int
        Most interactions per path (:attr:`Recipe.order`) of the added families.
    recipes, labels : tuple
        Per slot.
    specular, diffraction : tuple of int
        Slots of kind direct / spec, and diff.
    same_edge : tuple of (int, int)
        (diffraction + reflections slot, the plain diffraction slot over the same edge with the
        same ground bounce): the first is longer and has more losses (M-NLS's same-edge
        dominance, :mod:`diffpos.estimators.mnls.rules`).
    lit : tuple of int
        Per slot: the slot of the same path without its horizontal window-edge (sill or
        lintel) diffraction, the direct or specular path that edge cuts (at the edge's shadow
        boundary the two have the same length, the diffracted one existing on the shadow
        side, the other on the lit side), or -1 (no such edge or no such slot; M-NLS's
        boundary starts, :attr:`diffpos.estimators.mnls.rules.SnrRule.shadow_starts`).
    """

    max_order: int
    recipes: tuple[Recipe, ...]
    labels: tuple[str, ...] = field(init=False)
    specular: tuple[int, ...] = field(init=False)
    diffraction: tuple[int, ...] = field(init=False)
    same_edge: tuple[tuple[int, int], ...] = field(init=False)
    lit: tuple[int, ...] = field(init=False)

    def __post_init__(self) -> None:
        rec = self.recipes
        object.__setattr__(self, "labels", tuple(r.label for r in rec))
        object.__setattr__(self, "specular",
                           tuple(i for i, r in enumerate(rec) if r.kind != "diff"))
        object.__setattr__(self, "diffraction",
                           tuple(i for i, r in enumerate(rec) if r.kind == "diff"))
        plain = {(r.ground, r.edge): i for i, r in enumerate(rec)
                 if r.kind == "diff" and not r.planes}
        object.__setattr__(self, "same_edge", tuple(
            (i, plain[(r.ground, r.edge)]) for i, r in enumerate(rec)
            if r.kind == "diff" and r.planes and (r.ground, r.edge) in plain))
        index = {r: i for i, r in enumerate(rec)}
        object.__setattr__(self, "lit", tuple(
            index.get(Recipe("spec", r.ground, None, r.planes) if r.ground or r.planes
                      else Recipe("direct"), -1) if r.kind == "diff" and r.edge in ("upper", "lower")
            else -1 for r in rec))

    def __len__(self) -> int:
        return len(self.recipes)

    @property
    def max_planes(self) -> int:
        """Most inside reflections of a slot."""
        return max(len(r.planes) for r in self.recipes)


def _slab_series(n: int, first: str) -> tuple[str, ...]:
    """``n`` alternating floor / ceiling reflections starting with ``first``."""
    other = {"floor": "ceiling", "ceiling": "floor"}
    out: list[str] = []
    cur = first
    for _ in range(n):
        out.append(cur)
        cur = other[cur]
    return tuple(out)


def _families(max_order: int) -> list[Recipe]:
    """Every family with at most ``max_order`` interactions: an entry (straight, ground
    bounce, window-edge diffraction, ground bounce then diffraction), an image series between
    the floor and ceiling slabs (alternating; after a ground bounce straight through the window
    the ray rises, so the series starts at the ceiling), then at most one wall reflection
    (after at most :data:`WALL_AFTER_SLABS` slab reflections). The vertical window edges
    (:data:`VERTICAL_EDGES`) come last (the earlier families keep their slots) and take slab
    series only."""
    out: list[Recipe] = []
    entries = [Recipe("spec"), Recipe("spec", True)]
    entries += [Recipe("diff", g, e) for g in (False, True) for e in ("upper", "lower")]
    entries += [Recipe("diff", g, e) for g in (False, True) for e in VERTICAL_EDGES]
    for ent in entries:
        walls = () if ent.edge in VERTICAL_EDGES else WALLS
        firsts = ("ceiling",) if (ent.kind == "spec" and ent.ground) else ("floor", "ceiling")
        for n in range(max_order - ent.order + 1):
            series = {_slab_series(n, f) for f in firsts} if n else {()}
            for sl in sorted(series, key=lambda t: t[:1] != ("floor",)):
                out.append(ent._replace(planes=sl))
                if ent.order + n + 1 <= max_order and n <= WALL_AFTER_SLABS:
                    out += [ent._replace(planes=(*sl, w)) for w in walls]
    return [r for r in out if r.order > 0]


def _partition_families(max_order: int) -> list[Recipe]:
    """Every entry of :func:`_families` (incl. the vertical edges), then a slab series, then
    one partition reflection (its place among the slab reflections free: :class:`Recipe`), at
    most ``max_order`` interactions."""
    out: list[Recipe] = []
    entries = [Recipe("spec"), Recipe("spec", True)]
    entries += [Recipe("diff", g, e) for g in (False, True)
                for e in ("upper", "lower", *VERTICAL_EDGES)]
    for ent in entries:
        firsts = ("ceiling",) if (ent.kind == "spec" and ent.ground) else ("floor", "ceiling")
        for n in range(max_order - ent.order):
            series = sorted({_slab_series(n, f) for f in firsts} if n else {()},
                            key=lambda t: t[:1] != ("floor",))
            out += [ent._replace(planes=(*sl, "partition")) for sl in series]
    return out


def mechanism_set(max_order: int = DEFAULT_ORDER, *, partitions: bool = False) -> MechanismSet:
    """The 18 mechanisms of :data:`MECHANISMS`, then (``max_order`` > 2) every family of at
    most ``max_order`` interactions they leave out (:func:`_families`), in a fixed order;
    ``partitions``: then the partition-reflection families (:func:`_partition_families`; a
    building without partitions never has them), appended so every other family keeps its
    slot.

    ``max_order`` <= :data:`DEFAULT_ORDER` gives the 18 (a selection of the order-2
    mechanisms); 3 adds e.g. the ceiling-floor-ceiling triple bounce, the ground bounce before
    a window-edge diffraction, diffraction then two slab reflections; 4 the next terms.
    """
    if int(max_order) != max_order or max_order < 1:
        raise ValueError(f"max_order must be an integer >= 1; got {max_order!r}")
    if max_order <= DEFAULT_ORDER:
        return MechanismSet(max_order=DEFAULT_ORDER, recipes=RECIPES)
    known = set(RECIPES)
    extra = [r for r in _families(int(max_order)) if r not in known]
    if partitions:
        extra += _partition_families(int(max_order))
    return MechanismSet(max_order=int(max_order), recipes=(*RECIPES, *extra))


#: The families of first arrivals :func:`label_family` names, in report order.
FAMILIES: tuple[str, ...] = (
    "direct", "R x1", "R x2", "R x3+", "D", "D+R", "D+RR+", "ground+D", "vertical D",
    "wall/partition", "other", "none",
)
_SLABS = ("R(floor)", "R(ceiling)")
_WALL_TOKENS = ("R(back)", "R(side x1)", "R(side x2)", "R(partition)")
_VERTICAL_TOKENS = ("D(vertical)", *(f"D({e})" for e in VERTICAL_EDGES))


def label_family(label: str) -> str:
    """The family (:data:`FAMILIES`) of a mechanism label (``Tx-D(lower)-R(ceiling)-Rx``, a
    :attr:`Recipe.label` or a ray tracer's classified chain): ``direct``; reflections only
    (ground, floor, ceiling) entering through the window, by count (``R x1``, ``R x2``,
    ``R x3+``); a horizontal window-edge diffraction alone (``D``), then one (``D+R``) or more
    (``D+RR+``) slab reflections; a ground bounce before the diffraction (``ground+D``); a
    diffraction on a vertical window edge (a ray tracer's ``D(vertical)`` or the model's
    ``D(vertical x1)`` / ``D(vertical x2)``) with any ground / slab bounces (``vertical D``);
    any back / side wall or partition reflection (``wall/partition``); every other chain
    (another floor's edge, a transmission through concrete, diffuse) ``other``;
    ``""`` or ``"none"``: no first arrival (``none``)."""
    if label in ("", "none"):
        return "none"
    toks = label.split("-")[1:-1]
    if not toks:
        return "direct"
    known = {"R(ground)", "D(upper)", "D(lower)", *_SLABS, *_WALL_TOKENS, *_VERTICAL_TOKENS}
    if any(t not in known for t in toks):
        return "other"
    if any(t in _WALL_TOKENS for t in toks):
        return "wall/partition"
    diff = [i for i, t in enumerate(toks) if t.startswith("D(")]
    if any(toks[i] in _VERTICAL_TOKENS for i in diff):
        return "vertical D" if len(diff) == 1 else "other"
    if not diff:
        return ("R x1", "R x2", "R x3+")[min(len(toks), 3) - 1]
    if len(diff) > 1:
        return "other"
    if "R(ground)" in toks[:diff[0]]:
        return "ground+D"
    after = len(toks) - diff[0] - 1
    return ("D", "D+R", "D+RR+")[min(after, 2)]
