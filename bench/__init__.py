"""LMDP Light Transport benchmark suite (``make bench``, ``make bench-quick``): see ``bench/run.py``
and ``docs/benchmarks.md``. Not part of the extension (excluded from its zip)."""
