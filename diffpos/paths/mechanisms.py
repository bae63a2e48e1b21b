"""The first-arrival mechanisms of the path model: their labels, recipes and slot sets.

Plain data, importable without the compiled kernels (the tracker's and the fusion's settings
types use it, and ``diffpos VERB --help`` must not load numba); :mod:`diffpos.paths.model`
evaluates the mechanisms and :mod:`diffpos.paths.model_nb` holds their compiled twin (a test
checks the tables agree).
"""

from __future__ import annotations

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

#: The recipe of every slot: ("direct",), ("spec", planes, ground) or ("diff", edge, plane).
_RECIPES: tuple[tuple, ...] = (
    ("direct",),
    ("spec", (), True),
    ("spec", ("floor",), False),
    ("spec", ("ceiling",), False),
    ("spec", ("back",), False),
    ("spec", ("side x1",), False),
    ("spec", ("side x2",), False),
    ("diff", "upper", None),
    ("diff", "lower", None),
    ("diff", "upper", "floor"),
    ("diff", "upper", "ceiling"),
    ("diff", "lower", "floor"),
    ("diff", "lower", "ceiling"),
    ("diff", "upper", "back"),
    ("spec", ("ceiling",), True),
    ("spec", ("ceiling", "floor"), False),
    ("spec", ("floor", "ceiling"), False),
    ("spec", ("ceiling", "back"), False),
)
#: Slots whose last leg is a specular ray entering through the opening (incl. the direct one).
SPECULAR_SLOTS: tuple[int, ...] = (0, 1, 2, 3, 4, 5, 6, 14, 15, 16, 17)
#: Slots with a window-edge diffraction.
DIFFRACTION_SLOTS: tuple[int, ...] = (7, 8, 9, 10, 11, 12, 13)
_AXIS = {"floor": 2, "ceiling": 2, "back": 1, "side x1": 0, "side x2": 0, "ground": 2}
