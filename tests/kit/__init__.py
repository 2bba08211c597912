"""Tests of the top-level modules of course_lib (conventions, threads, paths), its command line and the notebook files."""
