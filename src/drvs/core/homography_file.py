"""Reading a camera's homography from a JSON or YAML file."""

from __future__ import annotations

from pathlib import Path

import yaml

from drvs.core._files import read_yaml
from drvs.core.errors import InvalidArgument
from drvs.core.geometry import Homography


def load_homography(path: str | Path) -> Homography:
    """The file's `homography` key: a 3x3 matrix (rows) or 9 numbers, row-major, image -> floor."""
    p = Path(path)
    data = read_yaml(p, "homography file")
    if not isinstance(data, dict) or "homography" not in data:
        raise InvalidArgument(f"homography file {p}: no 'homography' key")
    value = data["homography"]
    if isinstance(value, list) and len(value) == 3 and all(isinstance(r, list) for r in value):
        if any(len(r) != 3 for r in value):
            raise InvalidArgument(f"homography file {p}: 'homography' must be 3 rows of 3 numbers")
        value = [v for row in value for v in row]
    if not isinstance(value, list) or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
        raise InvalidArgument(f"homography file {p}: 'homography' must be a 3x3 list of numbers")
    return Homography.from_values(value, f"homography file {p}: homography")


def save_homography(path: str | Path, homography: Homography, **extra: object) -> None:
    rows = [[float(v) for v in row] for row in homography.matrix]
    Path(path).write_text(yaml.safe_dump({"homography": rows, **extra}, sort_keys=False))
