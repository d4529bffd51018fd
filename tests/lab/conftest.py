"""Shared fixtures for the lab's tests: the training tests' recorded files and small graph model."""

from __future__ import annotations

from tests.training.conftest import data, small_graph  # noqa: F401  (fixtures)
