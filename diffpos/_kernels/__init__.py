"""Compiled (numba) kernels of the hot paths; the numpy references stay beside each caller."""
