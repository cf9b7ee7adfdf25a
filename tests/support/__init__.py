"""Helpers the tests share, by part (a test module never imports another: tests/test_layout.py)."""
