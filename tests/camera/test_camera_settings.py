"""Each drvs-camera setting is declared once (a CameraConfig field made by `setting`): its flag, its
variable and its --config key (the field's name) all reach the same range check. This walks every
declaration, so a new setting is covered without editing this file."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import pytest

from drvs.camera.cli import build_parser
from drvs.camera.config import _FLAGS, ENVIRONMENT, LIMITS, SETTINGS, CameraConfig, Setting, load_config
from drvs.core.errors import InvalidArgument
from drvs.wire._cli import format_number

REQUIRED = ("--id", "cam1", "--source", "x.avi", "--homography", "h.yaml")
LIMITED = [s for s in SETTINGS.values() if s.limits is not None]


def below(s: Setting) -> float:
    assert s.limits is not None
    return s.limits[0] - 1


def test_every_field_is_declared_and_only_models_has_no_flag() -> None:
    assert list(SETTINGS) == [f.name for f in dataclasses.fields(CameraConfig)]
    assert {name for name, s in SETTINGS.items() if s.flag is None} == {"models"}
    assert set(LIMITS) == {s.name for s in LIMITED}
    assert {k for k, v in ENVIRONMENT.items() if v} <= set(_FLAGS)
    help_text = build_parser().format_help()
    for s in SETTINGS.values():
        assert s.flag is None or s.flag in help_text, s.flag


@pytest.mark.parametrize("s", [s for s in SETTINGS.values() if s.flag], ids=lambda s: s.flag)
def test_drvs_camera_parses_every_flag_into_its_setting_none_when_not_given(s: Setting) -> None:
    assert s.flag is not None
    parser = build_parser()
    assert getattr(parser.parse_args([]), s.name) is None
    takes_value = not isinstance(s.default, bool)
    args = parser.parse_args([s.flag, "1"] if takes_value else [s.flag])
    assert getattr(args, s.name) is not None


@pytest.mark.parametrize("s", LIMITED, ids=lambda s: s.name)
def test_every_limit_is_checked_from_flag_variable_and_config_file(s: Setting, tmp_path: Path) -> None:
    assert s.flag is not None
    value = format_number(below(s))
    origins: list[tuple[str, dict[str, Any], dict[str, str], Path | None]] = []
    args = vars(build_parser().parse_args([*REQUIRED, f"{s.flag}={value}"]))
    origins.append((s.flag, args, {}, None))
    base = vars(build_parser().parse_args(list(REQUIRED)))
    if s.env:
        origins.append((s.env, base, {s.env: value}, None))
    config = tmp_path / "cam.yaml"
    config.write_text(f"{s.name}: {value}\n")
    origins.append((f"config {config}", base, {}, config))
    for origin, flags, environ, config_file in origins:
        with pytest.raises(InvalidArgument) as err:
            load_config(flags, environ, config_file)
        assert str(err.value).startswith(f"{s.name} (from {origin}): {value} must be "), str(err.value)
