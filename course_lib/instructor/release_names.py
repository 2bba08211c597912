"""The student kit's text names only what ships: every module, name and file its prose points at exists there.

A student reads the released notebooks' markdown, the stubs' docstrings and the docstrings of the
kit's ``course_lib``, and follows what they name. :func:`dangling_references` collects what those
texts point at and checks it in the release itself:

* module paths and names, ``course_lib.sfm.lm.solve`` (also in Sphinx roles,
  ``:func:`~course_lib.nerf.rays.camera_rays```): the release's module must import and have the name;
* repository files, ``course_lib/sfm/fundamental.py``, ``benchmarks/ba_speed.py``: the file exists in the kit;
* short references in backquotes, ```lm.solve```, ```GridField.rebox```: when the first part is a
  module or a class of the kit, the second part exists there;
* unqualified Sphinx roles in the kit's docstrings, ``:func:`observation_list```: a top-level name
  of some module of the kit.

A reference in a paragraph that says "instructor" (``(in the instructor's kit)``) is marked as
instructor-only and not checked, there and in the rest of the same text (notebook cell, docstring).
"""

from __future__ import annotations

import ast
import io
import json
import os
import re
import subprocess
import sys
import tokenize
from pathlib import Path

import nbformat

__all__ = ["text_references", "dangling_references", "student_texts", "internal_references", "false_claims",
           "INTERNAL"]

#: Text that belongs to the kit's development, not to a student: issue numbers, dates, who measured what.
INTERNAL = re.compile(
    r"\bissues?\s*#?\d+|#\d+'s\b|\((?:H|helper )\d{1,3}(?:\)|, (?![WH]\d?\b))|\bH\d{1,3}, (?:20\d\d|several|one|two)\b"
    r"|\b20\d\d-[01]\d-[0-3]\d\b|\b(?:this|last|previous|earlier|next) session\b"
    # who worked on the kit: "the issue asks", "the team measured", "the lead", "helper sessions", branch names
    r"|\bthe (?:issue|team)\b|\b(?:the|our) lead\b|\bhelper(?:'s)? (?:session|branch)s?\b|\bwt-[a-z]+\b"
    r"|\bsession of 20\d\d\b", re.IGNORECASE)

_DOTTED = re.compile(r"(?<![\w/.])course_lib(?:\.\w+)+")
_PATH = re.compile(r"(?<![\w/.])(?:course_lib|notebooks|data|docs|benchmarks|tests|templates)/[\w./-]*\w")
_ROLE = re.compile(r":(?:func|class|meth|attr|mod|data|exc|obj):`~?([\w.]+)`")
_SHORT = re.compile(r"`(\w+)\.(\w+)(?:\(\))?`")


def _docstrings(src: str) -> list[tuple[int, str]]:
    """``(line, text)`` of the module, class and function docstrings of Python source (none if it does not parse)."""
    try:
        tree = ast.parse(src)
    except SyntaxError:
        return []
    out = []
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            body = getattr(node, "body", [])
            if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant) \
                    and isinstance(body[0].value.value, str):
                out.append((body[0].lineno, body[0].value.value))
    return out


def _comments(src: str) -> list[tuple[int, str]]:
    try:
        return [(t.start[0], t.string) for t in tokenize.generate_tokens(io.StringIO(src).readline)
                if t.type == tokenize.COMMENT]
    except (tokenize.TokenError, IndentationError, SyntaxError):
        return []


def text_references(out_dir: Path) -> list[dict]:
    """What the kit's texts point at: ``[{"where", "kind", "ref", "module"}]``.

    Texts: what a student reads (:func:`student_texts`), but the notebooks' outputs and the comments of the kit's
    modules; of a notebook's code cell, its docstrings and comments. ``kind`` is ``"dotted"``, ``"path"``,
    ``"short"`` or ``"name"``; ``module`` is the module whose docstring holds a ``"name"`` reference.
    """
    texts: list[tuple[str, str | None, str]] = []
    for where, mod, kind, text in student_texts(Path(out_dir)):
        if kind == "code":
            texts += [(f"{where}, line {ln}", mod, t) for ln, t in _docstrings(text) + _comments(text)]
        elif kind == "text":
            texts.append((where, mod, text))
    refs = []
    for where, mod, text in texts:
        marked: set[str] = set()
        for para in re.split(r"\n\s*\n", text):
            found = _references(para)
            if "instructor" in para.lower():  # marked as instructor-only: here and in the rest of this text
                marked |= {r for _, r in found}
                continue
            refs += [{"where": where, "kind": k, "ref": r, "module": mod} for k, r in found if r not in marked]
    return refs


def _references(text: str) -> list[tuple[str, str]]:
    """``[(kind, ref)]`` of one paragraph."""
    out = []
    for line in text.splitlines():
        found = [("dotted", m.group(0).rstrip(".")) for m in _DOTTED.finditer(line)]
        found += [("path", m.group(0).rstrip(".")) for m in _PATH.finditer(line)]
        for m in _ROLE.finditer(line):
            name = m.group(1)
            if not name.startswith("course_lib.") and name.rsplit(".", 1)[-1] not in _FILE_SUFFIXES:
                found.append(("name" if "." not in name else "short", name))
        found += [("short", f"{m.group(1)}.{m.group(2)}") for m in _SHORT.finditer(line)
                  if m.group(2) not in _FILE_SUFFIXES]
        out += found
    return out


_RESOLVE = r"""
import builtins, importlib, inspect, json, pkgutil, re, sys
import course_lib

refs = json.load(sys.stdin)
mods = {"course_lib": course_lib}
for m in pkgutil.walk_packages(course_lib.__path__, "course_lib."):
    mods[m.name] = importlib.import_module(m.name)
by_base = {}
for name, mod in mods.items():
    by_base.setdefault(name.rsplit(".", 1)[-1], []).append(mod)
top, classes = {}, {}
for mod in mods.values():
    for k, v in vars(mod).items():
        top.setdefault(k, []).append(v)
        if isinstance(v, type) and v.__module__.startswith("course_lib"):
            classes.setdefault(k, set()).add(v)


def members(cls):
    # attributes, dataclass fields, annotations, and what its methods assign to self
    names = set(dir(cls)) | set(getattr(cls, "__dataclass_fields__", {})) | set(getattr(cls, "__annotations__", {}))
    try:
        names |= set(re.findall(r"self\.(\w+)\s*(?:[:=]|\[)", inspect.getsource(cls)))
    except (OSError, TypeError):
        pass
    return names


all_members = set().union(*(members(c) for cs in classes.values() for c in cs)) if classes else set()


def has_path(obj, rest):
    parts = rest.split(".")
    for k, a in enumerate(parts):
        if isinstance(obj, type) and a in members(obj) and not hasattr(obj, a):
            return k == len(parts) - 1  # a field: nothing to follow
        if not hasattr(obj, a):
            return False
        obj = getattr(obj, a)
    return True


def dotted(ref):
    parts = ref.split(".")
    for n in range(len(parts), 0, -1):
        name = ".".join(parts[:n])
        if name in mods:
            return has_path(mods[name], ".".join(parts[n:])) if parts[n:] else True
    return False


missing = []
for r in refs:
    kind, ref = r["kind"], r["ref"]
    if kind == "dotted":
        ok = dotted(ref)
    elif kind == "name":
        ok = ref in top or ref in all_members or hasattr(builtins, ref) or (
            r["module"] in mods and hasattr(mods[r["module"]], ref))
    else:  # short: the first part a class of the kit (or, in the notebooks, a module): the rest is there
        first, rest = ref.split(".", 1)
        owners = list(classes.get(first, ()))
        if r["module"] is None:
            owners += by_base.get(first, [])
        ok = not owners or any(has_path(o, rest) for o in owners)
    if not ok:
        missing.append(r)
print(json.dumps(missing))
"""

#: second parts of ``a.b`` that make it a file name, not an attribute
_FILE_SUFFIXES = {"py", "pt", "tmp", "html", "json", "txt", "md", "png", "jpg", "gif", "ipynb", "npz", "npy", "csv",
                  "yml", "yaml", "toml", "bz2", "log"}


def dangling_references(out_dir: Path) -> list[str]:
    """The references of the kit's texts that the kit does not have, one line each (empty when all resolve).

    Imports the kit's own ``course_lib`` in a separate Python (``PYTHONPATH=out_dir``) to resolve them.
    """
    out_dir = Path(out_dir).resolve()
    refs = text_references(out_dir)
    problems = []
    to_resolve = []
    for r in refs:
        if r["kind"] == "path":
            if not (out_dir / r["ref"]).exists():
                problems.append(f"{r['where']}: names {r['ref']}, which the kit does not ship")
        else:
            to_resolve.append(r)
    env = dict(os.environ, PYTHONPATH=str(out_dir), MPLBACKEND="Agg")
    env.pop("COURSE_LIB_SOLUTIONS", None)
    res = subprocess.run([sys.executable, "-c", _RESOLVE], input=json.dumps(to_resolve), cwd=out_dir, env=env,
                         capture_output=True, text=True, timeout=300)
    if res.returncode != 0:
        return [f"the kit's course_lib does not import: {res.stderr.strip().splitlines()[-1:]}"]
    for r in json.loads(res.stdout.strip().splitlines()[-1]):
        problems.append(f"{r['where']}: names {r['ref']}, which the kit does not have")
    return sorted(set(problems))


def student_texts(root: Path, readme: str = "README.md") -> list[tuple[str, str | None, str, str]]:
    """``(where, module, kind, text)`` of everything a student reads in a kit at ``root`` (a release or the
    instructor's repo).

    ``kind``: ``"text"`` (the notebooks' markdown, ``README.md``, ``environment.txt``, ``docs/mistakes.md`` where
    present, the ``.md``/``.txt`` files of ``course_lib``, the docstrings of its modules, with ``module`` their
    module), ``"code"`` (a notebook's code cell), ``"output"`` (its text outputs: the verdicts and prints they show)
    or ``"comment"`` (a comment of a module). :mod:`course_lib.instructor` never ships and is not read.
    """
    root = Path(root)
    out: list[tuple[str, str | None, str, str]] = []
    for p in sorted((root / "notebooks").glob("*.ipynb")):
        nb = nbformat.read(p, as_version=4)
        for i, cell in enumerate(nb.cells):
            out.append((f"notebooks/{p.name}, cell {i}", None, "text" if cell.cell_type == "markdown" else "code",
                        cell.source))
            for o in cell.get("outputs", []):
                text = o.get("text") or (o.get("data") or {}).get("text/plain") or o.get("evalue") or ""
                out.append((f"notebooks/{p.name}, cell {i} (output)", None, "output",
                            text if isinstance(text, str) else "".join(text)))
    for name in (readme, "environment.txt", "docs/mistakes.md"):
        if (root / name).exists():
            out.append((name, None, "text", (root / name).read_text()))
    for p in sorted((root / "course_lib").rglob("*")):
        rel = p.relative_to(root)
        if "instructor" in rel.parts or p.suffix not in (".py", ".md", ".txt"):
            continue
        if p.suffix == ".py":
            src, mod = p.read_text(), ".".join(rel.with_suffix("").parts).removesuffix(".__init__")
            out += [(f"{rel}, line {ln}", mod, "text", t) for ln, t in _docstrings(src)]
            out += [(f"{rel}, line {ln}", mod, "comment", t) for ln, t in _comments(src)]
        else:
            out.append((str(rel), None, "text", p.read_text()))
    return out


def internal_references(root: Path, readme: str = "README.md") -> list[str]:
    """Where a student-read text of the kit at ``root`` cites the kit's development (:data:`INTERNAL`), one line each."""
    found = []
    for where, _, _, text in student_texts(root, readme):
        for m in INTERNAL.finditer(text):
            a, b = max(0, m.start() - 40), min(len(text), m.end() + 40)
            found.append(f"{where}: '{m.group(0)}' in ...{' '.join(text[a:b].split())}...")
    return found


_NUMBER_WORDS = {w: i for i, w in enumerate("zero one two three four five six seven eight nine ten eleven twelve".split())}


def false_claims(out_dir: Path) -> list[str]:
    """What the release's README and environment.txt say about the release that is not so, one line each.

    * "N notebooks" in ``README.md``: N is the number of notebooks the kit ships;
    * every pin of ``environment.txt`` is used: its package is imported by the kit's code or notebooks, or it
      is a tool the kit's README or pyproject uses (:data:`course_lib.instructor.release.STUDENT_TOOLS`);
    * no development text (:func:`internal_references`) in anything a student reads.
    """
    from course_lib.instructor.release import IMPORT_NAMES, STUDENT_TOOLS, imported_packages, requirement_name

    out_dir = Path(out_dir)
    problems = []
    n_nb = len(list((out_dir / "notebooks").glob("*.ipynb")))
    readme = (out_dir / "README.md").read_text() if (out_dir / "README.md").exists() else ""
    for m in re.finditer(r"\b(\d+|" + "|".join(_NUMBER_WORDS) + r")\s+(?:\w+\s+)?notebooks\b", readme, re.IGNORECASE):
        said = m.group(1).lower()
        n = int(said) if said.isdigit() else _NUMBER_WORDS[said]
        if n != n_nb:
            problems.append(f"README.md: says '{m.group(0)}', the kit ships {n_nb} notebooks")
    files = {str(p.relative_to(out_dir)): p.read_bytes() for p in out_dir.rglob("*")
             if p.is_file() and p.suffix in (".py", ".ipynb") and ".venv" not in p.parts}
    imported = imported_packages(files)
    env = out_dir / "environment.txt"
    for line in env.read_text().splitlines() if env.exists() else []:
        name = requirement_name(line)
        if name is None:
            continue
        if name in STUDENT_TOOLS:
            where, needle = STUDENT_TOOLS[name]
            ok = (out_dir / where).exists() and needle in (out_dir / where).read_text()
        else:
            ok = IMPORT_NAMES.get(name, name.replace("-", "_")) in imported
        if not ok:
            problems.append(f"environment.txt: pins {name}, which nothing in the kit uses")
    problems += internal_references(out_dir)
    return problems
