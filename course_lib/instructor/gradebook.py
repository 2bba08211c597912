"""The class's gradebook: one SQLite file with every grading of every submission, and its CSV export.

A row of ``gradings`` is one grading of one student's commit: when, by which version of the grader, with which
hidden seed, its status (``graded``, ``crashed``, ``timed out``), total, the feedback the student got and the whole
report; ``points`` holds its points per exercise. A regrade adds a row (the history stays); the export takes each
student's latest grading. As nbgrader's gradebook, it is a plain database that any SQLite client can read.
"""

from __future__ import annotations

import csv
import json
import sqlite3
from datetime import datetime, timezone
from pathlib import Path

__all__ = ["Gradebook"]

_SCHEMA = """
CREATE TABLE IF NOT EXISTS gradings (
    id INTEGER PRIMARY KEY, student TEXT NOT NULL, commit_id TEXT NOT NULL, graded_at TEXT NOT NULL,
    grader_version TEXT NOT NULL, hidden_seed INTEGER, status TEXT NOT NULL, total REAL NOT NULL, max REAL,
    seconds REAL, feedback TEXT NOT NULL, report TEXT NOT NULL);
CREATE INDEX IF NOT EXISTS gradings_of ON gradings (student, commit_id);
CREATE TABLE IF NOT EXISTS points (
    grading_id INTEGER NOT NULL REFERENCES gradings (id), notebook TEXT NOT NULL, exercise TEXT NOT NULL,
    points REAL NOT NULL, max_points REAL NOT NULL, status TEXT NOT NULL,
    PRIMARY KEY (grading_id, notebook, exercise));
"""


class Gradebook:
    """The gradebook in the SQLite file ``path`` (made when it does not exist)."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self.db = sqlite3.connect(self.path)
        self.db.row_factory = sqlite3.Row
        self.db.executescript(_SCHEMA)

    def close(self) -> None:
        self.db.close()

    def graded(self, student: str, commit: str) -> bool:
        """Whether this commit of this student has a finished grading (a crash or a timeout is graded again)."""
        row = self.db.execute("SELECT 1 FROM gradings WHERE student = ? AND commit_id = ? AND status = 'graded'",
                              (student, commit)).fetchone()
        return row is not None

    def record(self, student: str, commit: str, grader_version: str, status: str, report: dict,
               feedback: str) -> int:
        """Add one grading (its report as the grader wrote it, or the class runner's report of a crash); its id."""
        with self.db:
            cur = self.db.execute(
                "INSERT INTO gradings (student, commit_id, graded_at, grader_version, hidden_seed, status, total, max,"
                " seconds, feedback, report) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (student, commit, datetime.now(timezone.utc).isoformat(timespec="seconds"), grader_version,
                 report.get("hidden_seed"), status, float(report.get("total", 0.0)), report.get("max"),
                 report.get("seconds"), feedback, json.dumps(report, ensure_ascii=False)))
            self.db.executemany(
                "INSERT INTO points VALUES (?, ?, ?, ?, ?, ?)",
                [(cur.lastrowid, g["notebook"], g["name"], float(g["points"]), float(g["max_points"]), g["status"])
                 for g in report.get("exercises", [])])
        return int(cur.lastrowid)

    def latest(self) -> list[sqlite3.Row]:
        """Each student's latest grading (id, student, commit_id, graded_at, status, total, max), by student."""
        return self.db.execute(
            "SELECT id, student, commit_id, graded_at, status, total, max FROM gradings WHERE id IN "
            "(SELECT max(id) FROM gradings GROUP BY student) ORDER BY student").fetchall()

    def export_csv(self, path: Path) -> int:
        """Write one row per student (latest grading): total, then points per notebook, then per exercise (columns
        ``NOTEBOOK`` and ``NOTEBOOK: EXERCISE``), as LMS gradebooks import. Returns the number of rows."""
        rows = self.latest()
        points = {}
        for gid, nb, ex, pts in self.db.execute(
                "SELECT grading_id, notebook, exercise, points FROM points WHERE grading_id IN "
                f"({','.join('?' * len(rows))}) ORDER BY grading_id, rowid", [r["id"] for r in rows]):
            points[gid, nb, ex] = pts
        # the exercises in the grader's order (the notebook's), notebook by notebook
        exercises = sorted(dict.fromkeys((nb, ex) for _, nb, ex in points), key=lambda k: k[0])
        notebooks = sorted({nb for nb, _ in exercises})
        with open(path, "w", newline="") as f:
            out = csv.writer(f)
            out.writerow(["student", "commit", "graded_at", "status", "total", "max", *notebooks,
                          *(f"{nb}: {ex}" for nb, ex in exercises)])
            for r in rows:
                mine = {(nb, ex): p for (gid, nb, ex), p in points.items() if gid == r["id"]}
                out.writerow([r["student"], r["commit_id"], r["graded_at"], r["status"], _num(r["total"]),
                              _num(r["max"]),
                              *(_num(sum(p for (n, _), p in mine.items() if n == nb)) for nb in notebooks),
                              *(_num(mine.get(k, 0.0)) for k in exercises)])
        return len(rows)


def _num(x) -> str:
    return "" if x is None else f"{float(x):g}"
