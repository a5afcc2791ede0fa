"""Shared low-discrepancy sequences and warps of the unit square (float64 and float32)."""

#: 1/φ: the Kronecker sequence frac(i/φ) fills [0, 1) evenly.
GOLDEN = 0.6180339887498949
