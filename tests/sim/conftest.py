"""Fixtures of the simulation's tests."""

import importlib

import pytest


@pytest.fixture
def without_cffirmware(monkeypatch: pytest.MonkeyPatch) -> None:
    """As if the Crazyflie firmware's module were not built: importing it fails."""
    real = importlib.import_module

    def missing(name: str, package: str | None = None) -> object:
        if name == "cffirmware":
            raise ImportError("No module named 'cffirmware'")
        return real(name, package)

    monkeypatch.setattr(importlib, "import_module", missing)
