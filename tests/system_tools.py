"""System programs, libraries and files the tests need from Debian packages: a missing one
fails the test with the package to install (tools/install_system_packages.sh installs them
all), never skips it."""

from __future__ import annotations

import ctypes.util
import shutil
from pathlib import Path

import pytest

INSTALL = "run bash tools/install_system_packages.sh"


def _missing(what: str, package: str) -> None:
    pytest.fail(f"{what} is missing (Debian package {package}): {INSTALL}", pytrace=False)


def require_program(name: str, package: str) -> str:
    """The path of program `name`; fails the test when it is not on PATH."""
    path = shutil.which(name)
    if path is None:
        _missing(name, package)
    return path


def require_library(name: str, package: str) -> None:
    """Fails the test when shared library lib`name` cannot be found."""
    if ctypes.util.find_library(name) is None:
        _missing(f"the {name} library", package)


def require_path(path: Path, package: str) -> None:
    """Fails the test when `path` (a file or folder a package installs) does not exist."""
    if not Path(path).exists():
        _missing(str(path), package)
