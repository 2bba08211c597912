"""The stored fixtures are current: rebuilt from the reference, they equal the committed files."""

from course_lib.instructor.fixtures import build_fixtures


def test_fixtures_are_current():
    """Rebuild every fixture from the reference and compare with the committed files."""
    diffs = build_fixtures(write=False)
    assert diffs, "no case builders registered"
    stale = {k: v for k, v in diffs.items() if v}
    assert not stale, f"stale fixtures (run: python -m course_lib fixtures): {stale}"
