"""The report of a grading and the student's feedback: totals, the table of points, student text as plain data.

Feedback is data (:func:`to_markdown`): every text that can hold the student's words (messages of their exceptions,
names of their files) is shown in fenced blocks, each message and the whole feedback capped; the totals are written
by the grader above any of it. The report and the feedback both go through one sanitiser (:func:`plain_text`): no
control, format, bidi, private-use or tag character of the student's reaches either.
"""

from __future__ import annotations

import re
import unicodedata
from dataclasses import asdict

__all__ = ["grading_report", "to_markdown", "plain_text", "plain_data", "cap", "short", "exc_text",
           "MAX_MESSAGE_CHARS", "MAX_MESSAGES", "MAX_FEEDBACK_BYTES"]

#: Characters of one feedback message, messages of one exercise, and bytes of the whole Markdown feedback (a GitHub
#: comment holds 65 536 characters).
MAX_MESSAGE_CHARS, MAX_MESSAGES, MAX_FEEDBACK_BYTES = 600, 16, 60_000


def short(text: str, n: int = 160) -> str:
    text = " ".join(str(text).split())
    return text if len(text) <= n else text[: n - 3] + "..."


def cap(text: str, n: int = MAX_MESSAGE_CHARS) -> str:
    """``text`` on one line, plain (:func:`plain_text`), at most ``n`` characters (student text is data)."""
    text = " ".join(plain_text(str(text)).split())
    return text if len(text) <= n else text[: n - 30] + f" ... ({len(text) - n + 30} characters left out)"


def exc_text(exc: BaseException) -> str:
    return short(f"{type(exc).__name__}: {exc}", 300)


#: ANSI escape sequences (removed whole, so that no "[31m" is left behind).
_ANSI = re.compile(r"\x1b\[[0-9;?]*[ -/]*[@-~]|\x1b[@-_]")

#: Categories never shown from a student's text: controls, format characters (bidi marks and overrides, zero-width
#: joiners, the soft hyphen, U+061C, U+206A-F, U+FFF9-B, the tag characters U+E0000-E007F that spell hidden text),
#: surrogates, private use, unassigned code points, line and paragraph separators.
_HIDDEN_CATEGORIES = {"Cc", "Cf", "Cs", "Co", "Cn", "Zl", "Zp"}

#: Variation selectors (invisible, and a known way to smuggle bytes behind a visible character).
_SELECTORS = ((0xFE00, 0xFE0F), (0xE0100, 0xE01EF), (0x180B, 0x180F))


def _hidden_char(c: str) -> bool:
    o = ord(c)
    return unicodedata.category(c) in _HIDDEN_CATEGORIES or any(a <= o <= b for a, b in _SELECTORS)


def plain_text(text: str) -> str:
    """``text`` as plain data: ANSI escapes removed; every control, format (bidi, zero-width, soft hyphen, tag
    characters), surrogate, private-use, unassigned or separator character and variation selector written as its
    escape (``\\u202e``); tabs and newlines kept. The one sanitiser of everything the report and the feedback show."""
    text = _ANSI.sub("", text)
    if text.isascii():
        return _ASCII_CONTROL.sub(lambda m: _escape_char(m.group()), text)
    return "".join(_escape_char(c) if c not in "\t\n" and _hidden_char(c) else c for c in text)


_ASCII_CONTROL = re.compile(r"[\x00-\x08\x0b-\x1f\x7f]")


def _escape_char(c: str) -> str:
    o = ord(c)
    return f"\\x{o:02x}" if o < 0x100 else (f"\\u{o:04x}" if o < 0x10000 else f"\\U{o:08x}")


def plain_data(obj):
    """``obj`` (a report: dicts, lists, strings, numbers) with every string, keys included, made :func:`plain_text`."""
    if isinstance(obj, str):
        return plain_text(obj)
    if isinstance(obj, dict):
        return {plain_data(k): plain_data(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [plain_data(v) for v in obj]
    return obj


def grading_report(grades: list, salt: int, seconds: float, allow_reference: bool,
                   notes: dict[str, list[str]] | None = None) -> dict:
    """The report's totals, points per notebook (with its ``notes``) and per exercise (``grades``: the
    :class:`~course_lib.instructor.grade_plan.ExerciseGrade` of each), feedback capped."""
    notebooks = []
    for name in sorted({g.notebook for g in grades}):
        gs = [g for g in grades if g.notebook == name]
        notebooks.append({"notebook": name, "points": round(sum(g.points for g in gs), 2),
                          "max_points": round(sum(g.max_points for g in gs), 2),
                          "notes": [cap(n, 600) for n in (notes or {}).get(name, [])[:MAX_MESSAGES]]})
    return {
        "total": round(sum(g.points for g in grades), 2),
        "max": round(sum(g.max_points for g in grades), 2),
        "hidden_seed": salt,
        "instructor_self_test": allow_reference,
        "seconds": round(seconds, 1),
        "notebooks": notebooks,
        "exercises": [dict(asdict(g), feedback=[cap(f, 2000) for f in g.feedback[:MAX_MESSAGES]]) for g in grades],
    }


def to_markdown(report: dict) -> str:
    """Feedback for the student, as Markdown (also the GitHub job summary and the CI template's issue comment).

    Feedback is data: the grader writes the title, the totals and the table of points (exercise names come from the
    instructor's notebooks) before any text that can hold the student's words; every such text (the feedback
    messages, which quote the student's exceptions, and the names of their files) is shown in a fenced block whose
    fence is longer than any run of backticks in it, without control characters, each message at most
    :data:`MAX_MESSAGE_CHARS` characters and :data:`MAX_MESSAGES` per exercise; the whole feedback stays under
    :data:`MAX_FEEDBACK_BYTES` (the details of the last exercises are left out, saying so, past it).
    """
    report = plain_data(report)
    head = ["# Grading feedback", "", f"**Total: {report['total']:g} / {report['max']:g} points**", ""]
    if report.get("insecure"):
        head += ["**Graded with `--insecure`: your code ran without the grader's sandbox (a trusted local run).**", ""]
    head += ["| notebook | exercise | points | status | seconds |", "|---|---|---:|---|---:|"]
    for g in report["exercises"]:
        secs = g.get("hidden", {}).get("seconds")
        head.append(f"| {g['notebook']} | `{g['name']}` | {g['points']:g} / {g['max_points']:g} | {g['status']} | "
                    f"{'' if secs is None else format(secs, 'g')} |")
    head.append("")
    tail = [f"<sub>hidden seed {report['hidden_seed']}, graded in {report['seconds']:g} s{_sandbox_line(report)}"
            "</sub>", ""]
    left_out = report.get("submission", {}).get("left out", [])
    if left_out:
        tail = ["## Files of your submission the grader did not copy", "",
                *_fenced([cap(r, 300) for r in left_out[:20]]), ""] + tail
    budget = MAX_FEEDBACK_BYTES - len("\n".join(head + tail).encode()) - 400
    body: list[str] = []
    skipped = 0
    for nb in report["notebooks"]:
        part = [f"## {nb['notebook']}: {nb['points']:g} / {nb['max_points']:g}", ""]
        if nb.get("notes"):
            part += _fenced([f"- note: {cap(n)}" for n in nb["notes"]]) + [""]
        for g in (g for g in report["exercises"] if g["notebook"] == nb["notebook"]):
            part += [f"### `{g['name']}`: {g['points']:g} / {g['max_points']:g}", ""]
            lines = [f"- {cap(f)}" for f in g["feedback"][:MAX_MESSAGES]]
            if len(g["feedback"]) > MAX_MESSAGES:
                lines.append(f"- ... and {len(g['feedback']) - MAX_MESSAGES} more messages")
            if g["nbval"] != "not run":
                lines.append(f"- nbval check cell: {g['nbval']}")
            block = _fenced(lines) + [""] if lines else []
            if len("\n".join(body + part + block).encode()) > budget:
                skipped += 1
                block = ["*(details left out: the feedback is capped at "
                         f"{MAX_FEEDBACK_BYTES // 1000} kB; your instructor has them all)*", ""]
            part += block
        body += part
    return "\n".join(head + body + tail) + "\n"


def _fenced(lines: list[str]) -> list[str]:
    """``lines`` as one fenced block of plain text (a fence longer than any run of backticks inside)."""
    longest = max((len(m) for ln in lines for m in re.findall(r"`+", ln)), default=0)
    fence = "`" * max(3, longest + 1)
    return [fence + "text", *lines, fence]


def _sandbox_line(report: dict) -> str:
    """One line on what confined the student's code (from the report's ``isolation``)."""
    box = report.get("isolation", {}).get("hidden checks", {})
    if report.get("insecure"):
        return "; no sandbox (--insecure)"
    if not isinstance(box, dict) or not box:
        return ""
    if box.get("tool") == "container mode":
        return "; container mode: an unprivileged uid, no network, the hidden cases closed to it, totals"
    if box.get("namespaces") is True and box.get("read_only") is True:
        totals = "cgroup totals" if "whole process tree" in str(box.get("memory", "")) else "per-process limits"
        return f"; sandbox: bubblewrap, namespaces, no network, an allow-listed read-only file system, {totals}"
    return "; sandbox: unknown"
