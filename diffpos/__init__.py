"""diffpos: diffraction-aided wireless positioning (pure numerical core).

This package imports numpy and scipy only: no network, files, plots or viewers.
See DEVELOPING.md for the layout and conventions.
"""

from . import gtd, linkbudget
from .bounds import (
    Bounds,
    Identifiability,
    bounds_from_fim,
    fisher_information,
    identifiability,
    path_jacobian,
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
from .linkbudget import (
    db_to_linear,
    free_space_path_gain_db,
    noise_floor_dbm,
    ranging_crlb_m,
    snr_db,
)

__all__ = [
    "BOLTZMANN_J_K",
    "SPEED_OF_LIGHT_M_S",
    "Bounds",
    "DiffractionPoint",
    "EdgePath",
    "Identifiability",
    "bounds_from_fim",
    "db_to_linear",
    "diffracted_field",
    "diffraction_point",
    "fisher_information",
    "free_space_path_gain_db",
    "gtd",
    "identifiability",
    "lemma1_roots",
    "linkbudget",
    "los_path",
    "noise_floor_dbm",
    "path_jacobian",
    "position_error_bound",
    "power_ratio_approx",
    "power_ratio_exact",
    "ranging_crlb_m",
    "snr_db",
    "window_edge_fields",
    "window_edge_path",
]
__version__ = "0.1.0"
