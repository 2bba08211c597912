"""Test-suite settings shared by pytest and the nbval kernels it starts."""

import os

# Notebooks that train read this and use their quick setting, so the suite stays fast (README).
os.environ.setdefault("COURSE_LIB_QUICK", "1")
os.environ.setdefault("MPLBACKEND", "Agg")
