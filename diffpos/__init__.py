"""diffpos: diffraction-aided wireless positioning (pure numerical core).

This package imports numpy and scipy only: no network, files, plots or viewers.
See DEVELOPING.md for the layout and conventions.
"""

from . import gtd
from .bounds import (
    Bounds,
    Identifiability,
    fisher_information,
    identifiability,
    position_error_bound,
)
from .constants import BOLTZMANN_J_K, SPEED_OF_LIGHT_M_S
from .geometry import (
    DiffractionPoint,
    EdgePath,
    diffraction_point,
    lemma1_roots,
    los_path,
    window_edge_path,
)
from .gtd import (
    diffracted_field,
    power_ratio_approx,
    power_ratio_exact,
    window_edge_fields,
)

__all__ = [
    "BOLTZMANN_J_K",
    "SPEED_OF_LIGHT_M_S",
    "Bounds",
    "DiffractionPoint",
    "EdgePath",
    "Identifiability",
    "diffracted_field",
    "diffraction_point",
    "fisher_information",
    "gtd",
    "identifiability",
    "lemma1_roots",
    "los_path",
    "position_error_bound",
    "power_ratio_approx",
    "power_ratio_exact",
    "window_edge_fields",
    "window_edge_path",
]
__version__ = "0.1.0"
