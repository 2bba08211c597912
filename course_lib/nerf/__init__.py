"""NeRF, one module per component (notebooks 06-08): rays, encoding, model, render, train."""
