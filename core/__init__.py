"""The ESGS engine. Importable without ``bpy`` (a test enforces it).

Subpackages and modules each do one job; see docs/architecture.md.
"""
import os as _os

# Idle OpenMP threads spin by default; on a busy 2-core machine that tripled the CPU time of
# torch + Numba steps (measured in benchmarks/bench_rasterizer.py). Set before torch loads.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
