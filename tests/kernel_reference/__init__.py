"""Numpy oracles of compiled kernels whose numpy form is not an engine fallback (tests only)."""
