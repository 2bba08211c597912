"""``python -m course_lib refresh-checks [NOTEBOOK ...]``: store new check-cell verdicts in the notebooks.

nbval compares only the cells marked ``# NBVAL_CHECK_OUTPUT`` (``--nbval-lax``), and it runs the
notebooks in quick mode (``COURSE_LIB_QUICK=1``). When the wording of a check changes, only those
cells' stored outputs need to change; re-executing a whole notebook in full mode (minutes of NeRF
training for 08–10) would also replace every figure. This command executes each notebook in quick
mode, exactly as nbval will, and copies the outputs of the check cells, and only those, into the
stored notebook. A notebook whose code or figures changed should be re-executed whole instead
(``jupyter nbconvert --to notebook --execute --inplace``).

It refuses to store an error output, and says which check cells changed.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import nbformat

from course_lib.instructor.notebooks import CHECK_MARK, execute_quick
from course_lib.paths import REPO_ROOT
from course_lib.validate import KitInputError


def _text(outputs) -> str:
    return "".join(o.get("text", "") for o in outputs if o.get("output_type") == "stream")


def refresh_checks(path: Path, timeout: float = 600.0, write: bool = True) -> list[int]:
    """Execute ``path`` in quick mode and store its check cells' outputs; return the changed cell indices.

    Raises:
        KitInputError: a cell raised (nothing is written), or the notebook's cells changed while it ran.
    """
    path = Path(path)
    if not path.is_file():
        raise KitInputError(f"{path} is not a notebook file")
    stored = nbformat.read(path, as_version=4)
    run = nbformat.read(path, as_version=4)
    execute_quick(run, path.parent, timeout)
    errors = [(i, o) for i, c in enumerate(run.cells) if c.cell_type == "code"
              for o in c.outputs if o.output_type == "error"]
    if errors:
        i, o = errors[0]
        raise KitInputError(f"{path.name}: cell {i} raised {o.ename}: {o.evalue}; nothing was written")
    changed = []
    for i, (s, r) in enumerate(zip(stored.cells, run.cells)):
        if s.cell_type != "code" or not s.source.lstrip().startswith(CHECK_MARK):
            continue
        if _text(s.outputs) != _text(r.outputs):
            changed.append(i)
        s.outputs = r.outputs
        s.execution_count = r.execution_count
    if write and changed:
        nbformat.write(stored, path)
    return changed


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("notebooks", nargs="*", type=Path,
                   help="notebooks to refresh (default: every notebook in notebooks/)")
    p.add_argument("--check", action="store_true", help="only report which check cells would change; exit 1 if any")


def run(args) -> int:
    paths = args.notebooks or sorted((REPO_ROOT / "notebooks").glob("*.ipynb"))
    any_changed = False
    for p in paths:
        changed = refresh_checks(p, write=not args.check)
        any_changed |= bool(changed)
        state = "up to date" if not changed else ("stale" if args.check else "refreshed") + f": cells {changed}"
        print(f"{Path(p).name:40s} {state}")
    return 1 if (args.check and any_changed) else 0
