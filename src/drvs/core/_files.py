"""Reading the YAML/JSON files people write (homographies, calibration points, camera configs)."""

from __future__ import annotations

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
