"""Settings declared once: each a field of a role's frozen config dataclass, whose metadata holds its
whole declaration (flag, environment variable, help, argument group, and the role's own checks).

A dataclass with field metadata rather than pydantic-settings: no new dependency, and the messages,
precedence and argparse help people script against stay exactly as they are; pydantic would word
its own errors and want its own CLI. The roles (drvs.server.config, drvs.camera.config) subclass
`Setting` with what only they have (the server's ranges, the camera's limits and conversions) and
read their settings back with `declared`; this module is the part they share: the field, the flag,
the help and the parser's groups.
"""

from __future__ import annotations

import argparse
import dataclasses
from collections.abc import Callable, Iterable
from dataclasses import MISSING, dataclass
from typing import Any, TypeVar

#: The field metadata key that holds a setting's declaration.
KEY = "drvs.setting"

S = TypeVar("S", bound="Setting")
Parser = argparse.ArgumentParser | argparse._ArgumentGroup


@dataclass(frozen=True)
class Setting:
    """One setting's declaration. `flag`: its command-line flag; `env`: its environment variable;
    `help`: --help's text, with %(default)s (or %(default)g, …) and %(env)s filled in; `group`: its
    section of --help (None: the main list). `name` and `default` are the field's, filled in by
    `declared`."""

    flag: str | None = None
    env: str | None = None
    help: str = ""
    metavar: str | None = None
    group: str | None = None
    name: str = ""
    default: Any = None

    def help_text(self) -> str:
        """The help with its default and variable filled in (and escaped for argparse)."""
        return (self.help % {"default": self.default, "env": self.env}).replace("%", "%%")

    def flag_options(self) -> dict[str, Any]:
        """add_argument's options beyond dest, default and help (a role's kinds of flags)."""
        return {"metavar": self.metavar}

    def add_to(self, parser: Parser) -> None:
        """This setting's flag; not given, it is None (then the variable, file or default decide)."""
        assert self.flag is not None
        parser.add_argument(self.flag, dest=self.name, default=None, help=self.help_text(), **self.flag_options())


def field(declared: Setting, default: Any = MISSING, default_factory: Any = MISSING) -> Any:
    """A config dataclass field carrying `declared`. (It returns a dataclass field, so ruff's RUF009,
    a call as a default, raised where the type is not known immutable, is a false alarm there.)"""
    if default_factory is not MISSING:
        return dataclasses.field(default_factory=default_factory, metadata={KEY: declared})
    return dataclasses.field(default=default, metadata={KEY: declared})


def declared(
    config: type, empty: S, complete: Callable[[dataclasses.Field[Any], S], S] = lambda f, s: s
) -> dict[str, S]:
    """Every field's setting of the `config` dataclass by name, in its order, with its name and
    default (`empty` for a field declared without one); `complete` adds what the role derives from
    the field (its kind, say)."""
    settings: dict[str, S] = {}
    for f in dataclasses.fields(config):
        setting: S = f.metadata.get(KEY, empty)
        default = f.default if f.default is not MISSING else None
        settings[f.name] = complete(f, dataclasses.replace(setting, name=f.name, default=default))
    return settings


def add_arguments(parser: argparse.ArgumentParser, settings: Iterable[Setting]) -> None:
    """Each setting's flag (those without one skipped), in the given order, each in its group
    (created on first use)."""
    groups: dict[str | None, Parser] = {None: parser}
    for s in settings:
        if s.flag is not None:
            if s.group not in groups:
                groups[s.group] = parser.add_argument_group(s.group)
            s.add_to(groups[s.group])
