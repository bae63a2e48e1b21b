"""numpy's summation order in numba: so compiled kernels reproduce their numpy references bit
for bit. ``cache=True``; inlined into the kernels that call it (numba keys a kernel's cache on
its own file: after editing this one, clear ``diffpos/_kernels/__pycache__``)."""

from __future__ import annotations

from numba import njit


@njit(cache=True, error_model="numpy", nogil=True)
def pairwise_sum(a, n):
    """``numpy.sum`` of the first ``n`` (<= 128) values of ``a`` in numpy's order: its pairwise
    summation on a contiguous axis (a plain loop below 8 terms, else 8 accumulators; above 128
    numpy halves recursively, which callers leave to their reference path)."""
    if n < 8:
        res = 0.0
        for i in range(n):
            res += a[i]
        return res
    r0, r1, r2, r3, r4, r5, r6, r7 = a[0], a[1], a[2], a[3], a[4], a[5], a[6], a[7]
    i = 8
    while i < n - (n % 8):
        r0 += a[i]
        r1 += a[i + 1]
        r2 += a[i + 2]
        r3 += a[i + 3]
        r4 += a[i + 4]
        r5 += a[i + 5]
        r6 += a[i + 6]
        r7 += a[i + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += a[i]
        i += 1
    return res
