"""Test-suite settings shared by pytest and the nbval kernels it starts."""

import os

# Notebooks that train read this and use their quick setting, so the suite stays fast (README).
os.environ.setdefault("COURSE_LIB_QUICK", "1")
os.environ.setdefault("MPLBACKEND", "Agg")
# Many tiny BLAS calls (per-point solves) are slower with threads fighting over 2 cores.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
