"""Checks for the notebooks' exercises, fixtures, and (later) student release and grading."""
