"""Reading the YAML/JSON files people write (homographies, calibration points, camera configs), and
checking the folders the tools write into (drvs-office, drvs-certs, drvs-bench --out)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import yaml

from drvs.core.errors import InvalidArgument


def read_yaml(path: str | Path, label: str) -> Any:
    """The parsed file (YAML is a superset of JSON); InvalidArgument names the file on any failure."""
    p = Path(path)
    try:
        text = p.read_text()
    except OSError as exc:
        raise InvalidArgument(f"{label} {p}: {exc.strerror or exc}") from None
    except UnicodeDecodeError:
        raise InvalidArgument(f"{label} {p}: not a text file (expected JSON or YAML)") from None
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise InvalidArgument(f"{label} {p}: not JSON or YAML ({exc})") from None


def folder_problem(path: Path) -> str | None:
    """Why files could not be written into the folder `path` (made with its parents where missing),
    or None when they can. Asked before any work and without making anything, so that a run of
    minutes does not end on a folder it cannot make, and a refused command leaves nothing behind."""
    path = path.absolute()
    if path.exists() and not path.is_dir():
        return "it is there and is not a folder"
    there = path if path.exists() else next(p for p in path.parents if p.exists())
    if not there.is_dir():
        return f"{there} is not a folder"
    if not os.access(there, os.W_OK | os.X_OK):
        return f"{there} is not writable"
    return None
