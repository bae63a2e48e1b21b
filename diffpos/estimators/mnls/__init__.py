"""M-NLS: mechanism-aware non-linear least squares on the first-arrival path model."""
