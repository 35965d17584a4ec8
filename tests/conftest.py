"""Shared fixtures: small real scene stores built once per test session."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from hypothesis import settings

# CI explores the same examples every run (a failure there reproduces); locally they vary.
settings.register_profile("ci", derandomize=True, print_blob=True)
if os.environ.get("CI"):
    settings.load_profile("ci")

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


@pytest.fixture(scope="session")
def demo_store(tmp_path_factory) -> Path:
    """A small demo scene (same generator as ``walkstream build demo``), built once."""
    from server.scene.build import build_demo

    path = tmp_path_factory.mktemp("scenes") / "demo-small.db"
    build_demo(path, objects=24, seed=3)
    return path


@pytest.fixture(scope="session")
def denhaag_store(tmp_path_factory) -> Path:
    """A small Den Haag: buildings under an HLOD tree, a TIN terrain and tree groups, built once."""
    from server.scene.catalog import build_named

    path = tmp_path_factory.mktemp("scenes") / "denhaag-small.db"
    build_named("denhaag", path, seed=0, size=400)
    return path


@pytest.fixture(scope="session")
def auditorium_store(tmp_path_factory) -> Path:
    """The auditorium (``walkstream build auditorium``, seed 0): a hall of ≥ 400 detailed chairs, built once (~3 s)."""
    from server.scene.catalog import build_named

    path = tmp_path_factory.mktemp("scenes") / "auditorium.db"
    build_named("auditorium", path, seed=0)
    return path
