"""What every entry point shares: logging set-up, and SIGINT/SIGTERM turned into one shutdown event."""

from __future__ import annotations

import argparse
import asyncio
import os
import signal
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from drvs.core.errors import InvalidArgument
from drvs.wire import logs
from drvs.wire.security import Security

#: Log level for every role, e.g. DEBUG; --log-level overrides it.
ENV_LOG_LEVEL = "DRVS_LOG_LEVEL"


def env(name: str, default: str | None = None, environ: Mapping[str, str] = os.environ) -> str | None:
    """A DRVS_* environment variable, or the default (flags override both)."""
    value = environ.get(name)
    return value if value not in (None, "") else default


def env_number(name: str, default: float, *, integer: bool = False, environ: Mapping[str, str] = os.environ) -> float:
    """A numeric DRVS_* environment variable, or the default; InvalidArgument names the variable."""
    value = env(name, environ=environ)
    if value is None:
        return default
    try:
        return int(value) if integer else float(value)
    except ValueError:
        raise InvalidArgument(f"{name}: {value!r} is not {'an integer' if integer else 'a number'}") from None


def parse_bool(raw: object, where: str) -> bool:
    """A setting's true/false (1/0, yes/no, on/off, any case), or InvalidArgument naming `where`."""
    if isinstance(raw, bool):
        return raw
    text = str(raw).strip().lower()
    if text in ("1", "true", "yes", "on"):
        return True
    if text in ("0", "false", "no", "off"):
        return False
    raise InvalidArgument(f"{where}: {raw!r} is not true or false")


def format_number(value: float) -> str:
    """A setting's value or bound as messages show it: 1e7 rather than 1e+07."""
    return f"{value:g}".replace("e+0", "e").replace("e+", "e")


#: text (default) or json: one JSON object per line, with the request id on every hop.
ENV_LOG_FORMAT = "DRVS_LOG_FORMAT"


def setup_logging(level: str | None, fmt: str | None = None) -> None:
    logs.configure(
        level or env(ENV_LOG_LEVEL, "INFO") or "INFO", fmt or env(ENV_LOG_FORMAT, "text") or "text", sys.stderr
    )


def shutdown_event() -> asyncio.Event:
    """An event set by the first SIGINT or SIGTERM (containers send SIGTERM)."""
    event = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, event.set)
    return event


def join_negative_values(argv: list[str], options: tuple[str, ...]) -> list[str]:
    """Let `--roi -50,0,750,900` work: argparse would read a value starting with '-' as an option."""
    out: list[str] = []
    it = iter(argv)
    for arg in it:
        if arg in options:
            value = next(it, None)
            out.append(arg if value is None else f"{arg}={value}")
        else:
            out.append(arg)
    return out


#: The security settings every role takes, with their environment variables.
SECURITY_ENV = {
    "tls_cert": "DRVS_TLS_CERT",
    "tls_key": "DRVS_TLS_KEY",
    "tls_ca": "DRVS_TLS_CA",
    "tls_client_auth": "DRVS_TLS_CLIENT_AUTH",
    "token_file": "DRVS_TOKEN_FILE",
}


def add_security_arguments(p: argparse.ArgumentParser, token_help: str) -> None:
    """--tls-cert/--tls-key/--tls-ca/--tls-client-auth/--token-file; see drvs.wire.security."""
    g = p.add_argument_group("security (drvs-certs makes a development CA and certificates)")
    g.add_argument("--tls-cert", metavar="FILE", help="this role's certificate chain, PEM (env DRVS_TLS_CERT)")
    g.add_argument("--tls-key", metavar="FILE", help="its private key, PEM (env DRVS_TLS_KEY)")
    g.add_argument("--tls-ca", metavar="FILE", help="the CA that signs the peers' certificates (env DRVS_TLS_CA)")
    g.add_argument(
        "--tls-client-auth",
        action="store_const",
        const=True,
        help="mutual TLS: demand a certificate signed by --tls-ca from every caller (env DRVS_TLS_CLIENT_AUTH=1)",
    )
    g.add_argument("--token-file", metavar="FILE", help=f"{token_help} (env DRVS_TOKEN_FILE)")


def read_token(path: str | Path, what: str = "token_file") -> str:
    try:
        token = Path(path).read_text(encoding="utf-8").strip()
    except (OSError, UnicodeDecodeError) as exc:
        raise InvalidArgument(f"{what}: cannot read {path}: {exc}") from None
    if not token:
        raise InvalidArgument(f"{what}: {path} is empty")
    return token


def security_from(values: Mapping[str, Any], environ: Mapping[str, str] = os.environ) -> Security:
    """A Security from flag values (None = not given), falling back to the DRVS_* environment."""

    def get(name: str) -> Any:
        value = values.get(name)
        if value is None and environ.get(SECURITY_ENV[name], ""):
            value = environ[SECURITY_ENV[name]]
        return value

    client_auth = get("tls_client_auth")
    if isinstance(client_auth, str):
        client_auth = client_auth.strip().lower() in ("1", "true", "yes", "on")
    token_file = get("token_file")
    return Security(
        tls_cert=Path(get("tls_cert")) if get("tls_cert") else None,
        tls_key=Path(get("tls_key")) if get("tls_key") else None,
        tls_ca=Path(get("tls_ca")) if get("tls_ca") else None,
        require_client_cert=bool(client_auth),
        token=read_token(token_file) if token_file else "",
    )


def add_observability_arguments(p: argparse.ArgumentParser, metrics: bool = True) -> None:
    p.add_argument("--log-level", default=None, help="DEBUG, INFO, WARNING (env DRVS_LOG_LEVEL)")
    p.add_argument(
        "--log-format",
        choices=logs.FORMATS,
        default=None,
        help="text, or json: one object per line with the request id (env DRVS_LOG_FORMAT)",
    )
    if metrics:
        p.add_argument(
            "--metrics-port",
            default=None,
            metavar="[HOST:]PORT",
            help="serve Prometheus metrics on http://HOST:PORT/metrics (HOST: --metrics-host); 0 picks a free "
            "port (env DRVS_METRICS_PORT; default off)",
        )
        p.add_argument(
            "--metrics-host",
            default=None,
            metavar="HOST",
            help="address the metrics listen on when --metrics-port gives only a port "
            "(env DRVS_METRICS_HOST; default 127.0.0.1, this host only; 0.0.0.0 for every interface)",
        )
