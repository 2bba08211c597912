"""Pictures: plotly 3-D scenes, matplotlib figures and ipywidgets (the one place for them)."""
