"""Physical constants (SI, exact where the SI defines them)."""

SPEED_OF_LIGHT_M_S: float = 299_792_458.0
"""Speed of light in vacuum [m/s]."""

BOLTZMANN_J_K: float = 1.380_649e-23
"""Boltzmann constant [J/K]."""
