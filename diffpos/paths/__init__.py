"""The first-arrival path model: every mechanism's length, existence and Jacobian (``model``), compiled beside it (``model_nb``)."""
