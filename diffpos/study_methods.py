"""The names of the study's estimators and the defaults ``diffpos reproduce`` shows.

Kept apart from :mod:`diffpos.study` (which imports the estimators and their compiled
kernels): ``diffpos reproduce --help`` lists these choices without loading a kernel.
"""

from __future__ import annotations

__all__ = ["ALL_METHODS", "DEFAULT_QUICK_NODES", "METHOD_LABELS", "REPRODUCE_METHODS"]

#: method key -> label in tables and plots (``peb``: the position error bound, always computed)
METHOD_LABELS: dict[str, str] = {
    "lls": "LLS",
    "ippa": "IPPA",
    "dnls_case1": "D-NLS (Case-1)",
    "dnls_case2": "D-NLS (Case-2)",
    "dnls_lower": "D-NLS (lower edge)",
    "mnls": "M-NLS (first-arrival model)",
    "peb": "PEB",
}
#: every estimator the study can run (the keys of :data:`METHOD_LABELS` but ``peb``)
ALL_METHODS: list[str] = [k for k in METHOD_LABELS if k != "peb"]
#: ``diffpos reproduce``'s default estimators: the paper's four and M-NLS
REPRODUCE_METHODS: tuple[str, ...] = ("lls", "ippa", "dnls_case1", "dnls_case2", "mnls")
#: receivers kept by ``diffpos reproduce --quick``
DEFAULT_QUICK_NODES = 1500
