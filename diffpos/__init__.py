"""diffpos: diffraction-aided wireless positioning (pure numerical core).

This package imports numpy and scipy only: no network, files, plots or viewers. Every public
name has one import path, the module that defines it (no re-exports); DEVELOPING.md maps the
packages: ``paths`` (the first-arrival path model), ``channel`` (emulator, GTD/UTD, link
budget), ``estimators`` (LLS, IPPA, ``dnls``, ``mnls``), ``tracking`` (the per-responder
tracker), and the scorer, bounds, study and alignment modules.
"""

__version__ = "0.1.0"
