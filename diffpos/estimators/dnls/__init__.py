"""D-NLS: the paper's non-linear least squares on the window-edge diffraction path (solver, fit, compiled fit)."""
