"""Cheap checks of the committed notebook files (no kernel, no browser).

Every ``notebooks/*.ipynb`` is committed with its outputs, so that a student sees the figures
before running anything. These tests keep those files healthy:

* each file is smaller than 2 MB (plotly figures are stored as JSON through the
  ``plotly_mimetype`` renderer, never with a copy of plotly.js; point clouds are subsampled);
* no stored output is an error (a traceback committed by accident);
* every code cell has been executed (an execution count), in order, so the outputs belong to
  one top-to-bottom run;
* no plotly output embeds plotly.js (``text/html`` with a ``<script>`` of the library), which
  would mean the renderer was not the kit's.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

NOTEBOOKS = sorted((Path(__file__).resolve().parents[2] / "notebooks").glob("*.ipynb"))
MAX_BYTES = 2 * 1024 * 1024


def _load(path: Path) -> dict:
    return json.loads(path.read_text(encoding="utf-8"))


def _code_cells(nb: dict):
    return [(k, c) for k, c in enumerate(nb["cells"]) if c.get("cell_type") == "code"]


def test_there_are_notebooks():
    assert NOTEBOOKS, "no notebooks/*.ipynb found"


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_is_small(path):
    size = path.stat().st_size
    print(f"{path.name}: {size / 1024:.0f} kB")
    assert size < MAX_BYTES, (f"{path.name} is {size / 1e6:.2f} MB (limit 2 MB): subsample point clouds "
                              "(point_budget / max_points of course_lib.viz) or shrink images (dpi)")


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_has_no_error_outputs(path):
    errors = []
    for k, cell in _code_cells(_load(path)):
        for out in cell.get("outputs", []):
            if out.get("output_type") == "error":
                errors.append(f"cell {k}: {out.get('ename')}: {out.get('evalue')}")
    assert not errors, f"{path.name} is committed with error outputs:\n  " + "\n  ".join(errors)


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_was_run_top_to_bottom(path):
    counts = [(k, c.get("execution_count")) for k, c in _code_cells(_load(path)) if c.get("source")]
    missing = [k for k, n in counts if n is None]
    assert not missing, f"{path.name}: code cells {missing} have no execution count (commit the executed notebook)"
    numbers = [n for _, n in counts]
    assert numbers == sorted(numbers), f"{path.name}: cells were run out of order: execution counts {numbers}"


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_plotly_outputs_do_not_embed_plotly_js(path):
    bad = []
    for k, cell in _code_cells(_load(path)):
        for out in cell.get("outputs", []):
            html = out.get("data", {}).get("text/html", "")
            html = "".join(html) if isinstance(html, list) else html
            if "plotly" in html.lower() and ("<script" in html and len(html) > 100_000 or "cdn.plot.ly" in html):
                bad.append(k)
    assert not bad, (f"{path.name}: cells {bad} store plotly.js in the notebook (renderer 'notebook' or "
                     "'notebook_connected'); import course_lib.viz first, which selects 'plotly_mimetype'")
