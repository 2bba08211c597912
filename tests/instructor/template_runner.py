"""Run a GitHub Actions workflow's jobs here the way a stock runner does (for tests/instructor/test_template.py).

Each job gets a fresh workspace; its steps run in order: a ``run:`` step as a script of its own in
``bash --noprofile --norc -eo pipefail`` (with ``working-directory``, ``env``, ``GITHUB_ENV``, ``GITHUB_OUTPUT``,
``GITHUB_WORKSPACE`` and ``RUNNER_TEMP`` as on GitHub), a ``uses:`` step by a stand-in for the action:

* ``actions/checkout``: the files of ``repo_dir`` (the instructor's repository) into ``with.path``;
* ``actions/setup-python``: a fresh virtual environment first on ``PATH`` (see :func:`fresh_venv`);
* ``actions/upload-artifact`` / ``download-artifact``: a folder per artifact, links *followed* on upload (as v4
  does), ``pattern`` and ``merge-multiple`` on download.

``${{ }}`` expressions are evaluated (:func:`evaluate`: names, string literals, ``||``, ``&&``, ``==``, ``!=``,
``always()``, ``fromJSON``); the matrix is expanded from them; anything else fails the test, loudly.
"""

from __future__ import annotations

import fnmatch
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

_EXPR = re.compile(r"\$\{\{\s*(.*?)\s*\}\}")


def evaluate(expr: str, ctx: dict):
    """The value of a GitHub Actions expression (the part inside ``${{ }}``) in ``ctx`` (dotted names -> values)."""
    tokens = re.findall(r"'(?:[^']|'')*'|\|\||&&|==|!=|[(),]|[A-Za-z_][\w.\-]*", expr)
    if "".join(tokens).replace(" ", "") != expr.replace(" ", ""):
        raise ValueError(f"expression not understood by the runner: {expr!r}")
    pos = 0

    def peek():
        return tokens[pos] if pos < len(tokens) else None

    def take():
        nonlocal pos
        pos += 1
        return tokens[pos - 1]

    def primary():
        t = take()
        if t.startswith("'"):
            return t[1:-1].replace("''", "'")
        if t == "(":
            v = either()
            take()
            return v
        if peek() == "(":  # a function
            take()
            args = []
            while peek() != ")":
                args.append(either())
                if peek() == ",":
                    take()
            take()
            if t == "always":
                return True
            if t == "fromJSON":
                return json.loads(args[0])
            raise ValueError(f"function not known to the runner: {t}")
        if t not in ctx:
            return ""  # GitHub: a missing property is null, shown as ''
        return ctx[t]

    def compare():
        v = primary()
        while peek() in ("==", "!="):
            op, w = take(), primary()
            v = (v == w) if op == "==" else (v != w)
        return v

    def both():
        v = compare()
        while peek() == "&&":
            take()
            w = compare()
            v = w if v else v
        return v

    def either():
        v = both()
        while peek() == "||":
            take()
            w = both()
            v = v if v else w
        return v

    out = either()
    if pos != len(tokens):
        raise ValueError(f"expression not understood by the runner: {expr!r}")
    return out


def substitute(text, ctx: dict):
    """``text`` with each ``${{ }}`` replaced by its value (a lone expression keeps its type)."""
    if not isinstance(text, str):
        return text
    m = _EXPR.fullmatch(text.strip())
    if m:
        return evaluate(m.group(1), ctx)
    return _EXPR.sub(lambda m: _as_text(evaluate(m.group(1), ctx)), text)


def _as_text(v) -> str:
    return json.dumps(v) if isinstance(v, (list, dict)) else ("true" if v is True else "false" if v is False else str(v))


def fresh_venv(path: Path, deps_from: Path, python: str = sys.executable) -> Path:
    """A new virtual environment at ``path`` holding the distributions installed in ``deps_from`` (a site-packages
    folder) except the kit itself, as hard links (a copy where ``deps_from`` lies on another file system): so the
    template's own install line runs in full (pip finds the pinned dependencies satisfied and installs the kit,
    ``-e .``, from the folder it runs in) without unpacking 2 GB of wheels for each test run."""
    made = subprocess.run([python, "-m", "venv", str(path)], capture_output=True, text=True)
    assert made.returncode == 0, made.stdout + made.stderr
    site = next((path / "lib").glob("python3*/site-packages"))
    entries = [e.path for e in os.scandir(deps_from) if not os.path.lexists(site / e.name)
               and not re.match(r"(course_lib|__editable__)", e.name) and not e.name.endswith(".pth")]
    if entries and subprocess.run(["cp", "-al", *entries, str(site)], capture_output=True).returncode != 0:
        subprocess.run(["cp", "-a", *entries, str(site)], check=True)
    return path


class Runner:
    """Runs a workflow's jobs in ``root`` (a folder of its own per job; artifacts in ``root/artifacts``).

    Args:
        workflow: the parsed workflow.
        repo_dir: the repository the workflow lives in (what ``actions/checkout`` checks out).
        ctx: values of the expressions' names (``secrets.X``, ``vars.X``, ``github.event.inputs.X`` ...).
        path: ``PATH`` of the runner (stand-ins for ``gh``, ``sudo`` ... first).
        deps_from: the site-packages folder whose distributions the fresh venv sees (:func:`fresh_venv`).
        extra_files: files of the repository besides the kit's (``{"grading/roster.txt": text}``).
        extra_env: variables of the runner's environment (those the stand-ins read).
    """

    def __init__(self, workflow: dict, root: Path, repo_dir: Path, ctx: dict, path: str, deps_from: Path,
                 extra_files: dict | None = None, extra_env: dict | None = None):
        self.wf, self.root, self.repo_dir, self.ctx = workflow, Path(root), Path(repo_dir), dict(ctx)
        self.path, self.deps_from = path, deps_from
        self.extra_files, self.extra_env = extra_files or {}, extra_env or {}
        self.results: dict[str, str] = {}
        self.log: list[str] = []  # what ran, in order: "job[i]: step"

    def run_job(self, name: str) -> None:
        job = self.wf["jobs"][name]
        ctx = {**self.ctx, **{f"needs.{n}.result": self.results.get(n, "skipped") for n in self.wf["jobs"]}}
        if "if" in job and not evaluate(job["if"].removeprefix("${{").removesuffix("}}").strip(), ctx):
            self.results[name] = "skipped"
            return
        matrix = {k: substitute(v, ctx) for k, v in job.get("strategy", {}).get("matrix", {}).items()}
        combos = [{}] if not matrix else [{k: v} for k, vs in matrix.items() for v in vs]  # one axis is enough here
        ok = True
        for i, combo in enumerate(combos):
            job_ctx = {**ctx, "strategy.job-index": i, **{f"matrix.{k}": v for k, v in combo.items()}}
            ok &= self._run_steps(name, i, job, job_ctx)
        self.results[name] = "success" if ok else "failure"

    def _run_steps(self, name: str, index: int, job: dict, ctx: dict) -> bool:
        ws = self.root / f"{name}-{index}"
        (ws / "_temp").mkdir(parents=True)
        (ws / "work").mkdir()
        env_file, out_file = ws / "_temp" / "github_env", ws / "_temp" / "github_output"
        env = {"PATH": self.path, "HOME": str(ws / "_temp"), "LANG": "C.UTF-8", "GITHUB_WORKSPACE": str(ws / "work"),
               "RUNNER_TEMP": str(ws / "_temp"), "CI": "true", "GITHUB_ACTIONS": "true", **self.extra_env}
        failed = False
        for k, step in enumerate(job["steps"]):
            cond = step.get("if")
            if (failed and not (cond and "always()" in cond)) or (cond and not evaluate(cond, ctx)):
                continue
            env_file.write_text("")
            out_file.write_text("")
            step_env = {**env, **{k2: _as_text(substitute(v, ctx)) for k2, v in step.get("env", {}).items()},
                        "GITHUB_ENV": str(env_file), "GITHUB_OUTPUT": str(out_file)}
            self.log.append(f"{name}[{index}]: {step.get('name') or step.get('uses')}")
            if "uses" in step:
                with_ = {k2: substitute(v, ctx) for k2, v in step.get("with", {}).items()}
                self._action(step["uses"].split("@")[0], with_, ws, env)
                continue
            script = ws / "_temp" / f"step{k}.sh"
            script.write_text(substitute(step["run"], ctx))
            cwd = ws / "work" / step.get("working-directory", "")
            rc = subprocess.run(["bash", "--noprofile", "--norc", "-eo", "pipefail", str(script)], cwd=cwd,
                                env=step_env).returncode
            if rc != 0:
                self.log.append(f"{name}[{index}]: FAILED with exit status {rc}")
                failed = True
                continue
            env.update(_key_values(env_file.read_text()))
            if "id" in step:
                for key, value in _key_values(out_file.read_text()).items():
                    self.ctx[f"steps.{step['id']}.outputs.{key}"] = ctx[f"steps.{step['id']}.outputs.{key}"] = value
        for key, value in job.get("outputs", {}).items():
            self.ctx[f"needs.{name}.outputs.{key}"] = substitute(value, ctx)
        return not failed

    def _action(self, action: str, with_: dict, ws: Path, env: dict) -> None:
        work, artifacts = ws / "work", self.root / "artifacts"
        if action == "actions/checkout":
            dst = work / with_.get("path", "")
            files = subprocess.run(["git", "-C", str(self.repo_dir), "ls-files", "-co", "--exclude-standard", "-z"],
                                   capture_output=True, check=True).stdout.decode().split("\0")
            for rel in filter(None, files):
                src = self.repo_dir / rel
                if src.is_file() and (not with_.get("sparse-checkout") or rel.startswith(with_["sparse-checkout"])
                                      or "/" not in rel):
                    (dst / rel).parent.mkdir(parents=True, exist_ok=True)
                    shutil.copy2(src, dst / rel, follow_symlinks=False)
            for rel, text in self.extra_files.items():
                (dst / rel).parent.mkdir(parents=True, exist_ok=True)
                (dst / rel).write_text(text)
        elif action == "actions/setup-python":
            venv = fresh_venv(ws / "_tool" / "python", self.deps_from)
            env["PATH"] = f"{venv / 'bin'}:{env['PATH']}"
        elif action == "actions/upload-artifact":
            src = work / with_["path"]
            if src.exists():  # v4 follows symbolic links: what it uploads is their targets' content
                shutil.copytree(src, artifacts / with_["name"], symlinks=False, dirs_exist_ok=True)
        elif action == "actions/download-artifact":
            names = [with_["name"]] if "name" in with_ else sorted(
                p.name for p in artifacts.iterdir() if fnmatch.fnmatch(p.name, with_["pattern"]))
            for n in names:
                dst = work / with_["path"] / ("" if "name" in with_ or with_.get("merge-multiple") else n)
                shutil.copytree(artifacts / n, dst, dirs_exist_ok=True)
        else:
            raise ValueError(f"action not known to the runner: {action}")


def _key_values(text: str) -> dict:
    """``KEY=VALUE`` lines and ``KEY<<EOF`` blocks of GITHUB_ENV / GITHUB_OUTPUT."""
    out, lines = {}, iter(text.splitlines())
    for line in lines:
        if "<<" in line and "=" not in line.split("<<")[0]:
            key, end = line.split("<<", 1)
            out[key] = "\n".join(iter(lambda: next(lines), end))
        elif "=" in line:
            key, value = line.split("=", 1)
            out[key] = value
    return out
