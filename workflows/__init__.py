"""Workflows a user runs on their own scans with the library's Python API (``python -m workflows.NAME``)."""
