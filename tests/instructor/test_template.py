"""The CI template (templates/github-actions-grade.yml) runs, job by job, as on a stock runner.

:mod:`tests.instructor.template_runner` executes its ``plan``, ``grade`` and ``publish`` jobs from a fresh
workspace with the kit checked out into ``kit/`` and a fresh virtual environment, with ``gh`` answered by a
stand-in that serves three students' repositories (GitHub's tarballs of commits made from the student release)
and records what ``publish`` posts. Each submission must get ``report.json`` and ``feedback.md``, and a student's
link to another student's folder must be refused by name (the template passes tarballs, so the artifact upload
never follows it).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import sysconfig
import textwrap
from pathlib import Path

import pytest

from course_lib.__main__ import main
from course_lib.paths import REPO_ROOT
from tests.instructor.template_runner import Runner, evaluate

yaml = pytest.importorskip("yaml")  # installed with jupyterlab (jupyter_events)

#: The CI template's jobs in a fresh workspace take most of a minute: left out of the quick subset
#: (pytest -m "not slow").
pytestmark = pytest.mark.slow

TEMPLATE = REPO_ROOT / "templates" / "github-actions-grade.yml"
STUDENTS = {"ada/kit": "a" * 40, "bob/kit": "b" * 40, "cy/kit": "c" * 40}

FAKE_GH = textwrap.dedent("""\
    #!{python}
    # A stand-in for the GitHub CLI: serves the students' repositories, records what is posted.
    import json, os, sys
    state = json.load(open(os.environ["FAKE_GH_STATE"]))
    args = sys.argv[1:]
    with open(os.environ["FAKE_GH_LOG"], "a") as log:
        log.write(json.dumps({{"args": args, "token": os.environ.get("GH_TOKEN", ""),
                              "body": open(args[args.index("--body-file") + 1]).read() if "--body-file" in args
                              else None}}) + "\\n")
    if args[:1] == ["api"]:
        parts = args[1].split("/")
        repo = "/".join(parts[1:3])
        if parts[3:5] == ["commits", "HEAD"]:
            print(state[repo]["sha"])
        elif parts[3] == "commits" and parts[5:] == ["statuses"]:
            print(0)
        elif parts[3] == "tarball":
            sys.stdout.buffer.write(open(state[repo]["tarball"], "rb").read())
    elif args[:2] == ["issue", "create"]:
        print("https://github.com/" + args[args.index("-R") + 1] + "/issues/1")
    """)


def make_repositories(tmp: Path) -> dict:
    """Each student's repository: the student release with notebook 01 as they left it, as GitHub's tarball."""
    from tests.instructor.test_grade import NB01, solved

    import nbformat

    assert main(["release", str(tmp / "release")]) == 0
    state = {}
    for repo, sha in STUDENTS.items():
        owner = repo.split("/")[0]
        top = tmp / "stage" / owner / f"{owner}-kit-{sha[:7]}"  # GitHub's tarball: one folder, owner-repo-sha
        shutil.copytree(tmp / "release", top)
        if owner != "bob":  # bob hands in the untouched release
            nbformat.write(solved()[NB01], top / "notebooks" / NB01)
        if owner == "cy":  # cy links to another student's folder as it will lie beside theirs on the grader
            os.symlink("../../ada__kit/notebooks", top / "notebooks" / "ada")
        tarball = tmp / "stage" / f"{owner}.tar.gz"
        subprocess.run(["tar", "-czf", str(tarball), "-C", str(top.parent), top.name], check=True)
        state[repo] = {"sha": sha, "tarball": str(tarball)}
    return state


def runner_path(tmp: Path, state: dict, sudo: bool) -> str:
    bin_dir = tmp / "bin"
    bin_dir.mkdir()
    (bin_dir / "gh").write_text(FAKE_GH.format(python=sys.executable))
    if sudo:  # logs, then runs the command
        (bin_dir / "sudo").write_text(f'#!/bin/bash\necho "$*" >> {tmp}/sudo.log\nexec "$@"\n')
    for f in bin_dir.iterdir():
        f.chmod(0o755)
    (tmp / "gh-state.json").write_text(json.dumps(state))
    return f"{bin_dir}:/usr/local/bin:/usr/bin:/bin"


def test_the_template_grades_and_publishes_from_a_fresh_workspace(tmp_path):
    state = make_repositories(tmp_path)
    path = runner_path(tmp_path, state, sudo=False)
    wf = yaml.safe_load(TEMPLATE.read_text())
    ctx = {"secrets.STUDENT_REPOS_READ": "read-token", "secrets.STUDENT_REPOS_WRITE": "write-token",
           "vars.GRADE_OPTIONS": "--notebooks 01 --no-nbval --timeout 20"}
    runner = Runner(wf, tmp_path / "runner", REPO_ROOT, ctx, path, Path(sysconfig.get_paths()["purelib"]),
                    extra_files={"grading/roster.txt": "# the class\nada/kit\nbob/kit  # late\ncy/kit\n"},
                    extra_env={"FAKE_GH_STATE": str(tmp_path / "gh-state.json"),
                               "FAKE_GH_LOG": str(tmp_path / "gh.log")})
    for job in ("plan", "grade", "publish"):
        runner.run_job(job)
    print("\n".join(runner.log))  # the steps that ran (pytest -s)
    assert runner.results == {"plan": "success", "grade": "success", "publish": "success"}, runner.log

    feedback = tmp_path / "runner" / "artifacts" / "grading-0"
    reports = {s: json.loads((feedback / s / "report.json").read_text()) for s in ("ada__kit", "bob__kit", "cy__kit")}
    assert all((feedback / s / "feedback.md").is_file() for s in reports)
    assert reports["ada__kit"]["total"] == reports["cy__kit"]["total"] > 0 and reports["bob__kit"]["total"] == 0
    assert any(r.startswith("notebooks/ada: a symbolic link") for r in reports["cy__kit"]["submission"]["left out"])
    assert (feedback / "grades-0.sqlite").is_file() and len((feedback / "grades-0.csv").read_text().splitlines()) == 4

    calls = [json.loads(ln) for ln in (tmp_path / "gh.log").read_text().splitlines()]
    posted = {c["args"][c["args"].index("-R") + 1]: c["body"] for c in calls if c["args"][:2] == ["issue", "comment"]}
    assert set(posted) == set(STUDENTS)
    for repo, body in posted.items():
        assert "# Grading feedback" in body and f"commit {STUDENTS[repo]}" in body
    statuses = [c["args"] for c in calls if c["args"][0] == "api" and "/statuses/" in c["args"][1]
                and "-f" in c["args"]]
    assert sorted(s[1] for s in statuses) == sorted(f"repos/{r}/statuses/{sha}" for r, sha in STUDENTS.items())
    assert all("state=success" in s for s in statuses)
    assert {c["token"] for c in calls if c["args"][:2] == ["issue", "comment"]} == {"write-token"}
    assert {c["token"] for c in calls if c["args"][0] == "api" and "/tarball/" in c["args"][1]} == {"read-token"}


@pytest.mark.fails_closed  # no grading
@pytest.mark.parametrize("sudo", [False, True])
def test_the_setup_steps_run_with_or_without_sudo(tmp_path, sudo):
    """The grade job's first steps (bubblewrap, the delegated cgroup) pass with a sudo and without one (as root in a
    container, where the grader makes its cgroups itself)."""
    wf = yaml.safe_load(TEMPLATE.read_text())
    steps = [s for s in wf["jobs"]["grade"]["steps"] if "run" in s][:2]
    wf = {"jobs": {"grade": {"steps": steps}}}
    runner = Runner(wf, tmp_path / "runner", REPO_ROOT, {}, runner_path(tmp_path, {}, sudo), Path("/nonexistent"))
    runner.run_job("grade")
    assert runner.results == {"grade": "success"}, runner.log


@pytest.mark.fails_closed
def test_the_runner_evaluates_the_templates_expressions():
    ctx = {"github.event.inputs.repository": "", "github.event.client_payload.repository": "a/b",
           "needs.plan.outputs.shards": '["a b", "c"]', "needs.grade.result": "failure"}
    assert evaluate("github.event.inputs.repository || github.event.client_payload.repository || ''", ctx) == "a/b"
    assert evaluate("fromJSON(needs.plan.outputs.shards)", ctx) == ["a b", "c"]
    assert evaluate("needs.plan.outputs.shards != '[]'", ctx) is True
    assert evaluate("always() && needs.grade.result != 'skipped'", ctx) is True
    with pytest.raises(ValueError, match="not known"):
        evaluate("hashFiles('x')", ctx)
