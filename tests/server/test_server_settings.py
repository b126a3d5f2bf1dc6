"""Each drvs-server setting is declared once (a ServerConfig field made by `setting`), and the flag,
the DRVS_* variable, the range check and DrvsServer's keyword all come from that declaration: this
walks every declaration, so a new setting is covered without editing this file."""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
from typing import Any

import pytest

from drvs.core.errors import InvalidArgument
from drvs.server import DrvsServer
from drvs.server.cli import build_parser, config_from
from drvs.server.config import ENVIRONMENT, FLAGS, SETTINGS, ServerConfig, Setting, described
from drvs.wire._cli import format_number

RANGED = [s for s in SETTINGS.values() if s.range is not None]
WITH_ENV = [s for s in SETTINGS.values() if s.env is not None]


def below(s: Setting) -> float:
    """A value just outside the setting's range, at the low end."""
    assert s.range is not None
    low = s.range[0]
    return low - 1 if s.low_allowed else low


def flag_value(s: Setting) -> str:
    """A value the flag's parser takes, as typed on a command line."""
    if s.range is not None:
        return str(int(s.range[1])) if s.integer else repr(float(s.range[1]))
    return "10.0.0.0/8" if s.kind is tuple else "text"


def test_every_field_is_a_declared_setting_and_only_default_max_range_m_has_no_flag() -> None:
    assert list(SETTINGS) == [f.name for f in dataclasses.fields(ServerConfig)]
    assert {name for name, s in SETTINGS.items() if s.flag is None} == {"default_max_range_m"}
    for s in SETTINGS.values():
        assert s.kind in (bool, int, float, str, tuple), s
        assert s.flag is None or (s.flag.startswith("--") and s.help), s
    # The flags and variables people script against are all still there.
    assert set(FLAGS.values()) >= {
        "--listen", "--lease-ttl", "--forward-timeout", "--max-queued-forwards", "--allow-callback",
        "--allow-any-callback", "--warm-up", "--rate-limit", "--max-continuous", "--max-forward-bytes",
        "--max-streams-per-connection", "--max-connection-idle", "--max-connection-age",
        "--max-connection-age-grace", "--trust-network", "--registration-grace", "--max-cameras-per-identity",
        "--max-fov-range", "--max-fov-area", "--pose-lease", "--max-pose-lease", "--min-pose-interval",
        "--registry", "--registration-rate", "--pose-write-rate", "--advertise", "--etcd-ca", "--etcd-cert",
        "--etcd-key", "--workers", "--admission-target", "--max-pending-calls",
    }  # fmt: skip
    assert ENVIRONMENT == {
        "listen": "DRVS_SERVER_LISTEN",
        "lease_ttl_s": "DRVS_LEASE_TTL",
        "trust_network": "DRVS_TRUST_NETWORK",
        "registry": "DRVS_REGISTRY",
        "advertise": "DRVS_SERVER_ADVERTISE",
        "etcd_ca": "DRVS_ETCD_CA",
        "etcd_cert": "DRVS_ETCD_CERT",
        "etcd_key": "DRVS_ETCD_KEY",
    }


@pytest.mark.parametrize("s", [s for s in SETTINGS.values() if s.flag], ids=lambda s: s.flag)
def test_drvs_server_parses_every_flag_into_its_setting(s: Setting) -> None:
    assert s.flag is not None
    parser = build_parser()
    args = parser.parse_args([s.flag] if s.kind is bool else [s.flag, flag_value(s)])
    given = getattr(args, s.name)
    expected: dict[type, Any] = {bool: True, tuple: ["10.0.0.0/8"], str: "text"}
    assert given == (expected[s.kind] if s.kind in expected else s.kind(flag_value(s)))
    # Not given, a flag is None: the variable, then the default, decide.
    assert getattr(parser.parse_args([]), s.name) is None
    assert s.flag in parser.format_help()


def test_no_flag_given_is_the_defaults() -> None:
    assert config_from(build_parser().parse_args([])) == ServerConfig.load({}, {}) == ServerConfig()


@pytest.mark.parametrize("s", RANGED, ids=lambda s: s.name)
def test_every_range_is_checked_alike_by_flag_and_keyword(s: Setting) -> None:
    assert s.flag is not None and s.range is not None
    value = below(s)
    shown = format_number(value)
    with pytest.raises(InvalidArgument) as from_flag:
        config_from(build_parser().parse_args([f"{s.flag}={shown}"]))
    message = str(from_flag.value)
    interval = f"{'[' if s.low_allowed else '('}{format_number(s.range[0])}, {format_number(s.range[1])}]"
    assert message == f"{described(s.name)}: {shown} must be in {interval}{s.unit}"
    assert message.startswith(f"{s.name} ({s.flag}")
    keywords: dict[str, Any] = {s.name: value}
    with pytest.raises(InvalidArgument) as from_keyword:
        DrvsServer("127.0.0.1:0", **keywords)
    assert str(from_keyword.value) == message
    # The highest is allowed (other settings' rules aside); an integer setting refuses a fraction.
    s.check_range(s.range[1])
    if s.integer:
        with pytest.raises(InvalidArgument, match=" must be in "):
            s.check_range(s.range[1] - 0.5)


@pytest.mark.parametrize("s", WITH_ENV, ids=lambda s: s.env)
def test_every_variable_is_read_and_a_flag_wins_over_it(s: Setting) -> None:
    assert s.env is not None
    bad = {bool: "maybe", int: "x", float: "x"}.get(s.kind, "nowhere")
    with pytest.raises(InvalidArgument) as err:
        ServerConfig.load({}, {s.env: bad})
    assert s.env in str(err.value)
    # Given the flag too, the flag's value is taken and the variable not read at all.
    good = True if s.kind is bool else s.default
    assert getattr(ServerConfig.load({s.name: good}, {s.env: bad}), s.name) == good


def test_drvs_server_takes_every_setting_as_a_keyword_and_names_an_unknown_one() -> None:
    server = DrvsServer("127.0.0.1:0", pose_lease_s=2, max_pose_lease_s=20, registration_rate=5)
    assert (server.config.pose_lease_s, server.config.max_pose_lease_s) == (2, 20)
    assert server.config == ServerConfig(listen="127.0.0.1:0", pose_lease_s=2, max_pose_lease_s=20, registration_rate=5)
    with pytest.raises(TypeError, match="lease_ttl"):
        DrvsServer(lease_ttl=5)


@pytest.mark.parametrize(
    ("args", "env", "message"),
    [
        (("--min-pose-interval=-1",), {}, "min_pose_interval_s (--min-pose-interval): -1 must be in [0, 3600] seconds"),
        ((), {"DRVS_REGISTRY": "nowhere"}, "registry (--registry, DRVS_REGISTRY): 'nowhere' is not "),
    ],
    ids=["flag", "variable"],
)
def test_a_real_drvs_server_refuses_from_the_declaration(
    args: tuple[str, ...], env: dict[str, str], message: str
) -> None:
    environ = {k: v for k, v in os.environ.items() if not k.startswith("DRVS_")} | env
    proc = subprocess.run(
        [sys.executable, "-m", "drvs.server.cli", "--listen", "127.0.0.1:0", *args],
        env=environ,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith(f"drvs-server: error: {message}"), last
