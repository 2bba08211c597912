"""Structure from Motion, one module per step (and per notebook 01-05)."""
