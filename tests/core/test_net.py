"""host:port parsing: every malformed address is InvalidArgument naming the field."""

from __future__ import annotations

import pytest

from drvs.core.errors import InvalidArgument
from drvs.core.net import format_address, parse_address


@pytest.mark.parametrize(
    ("address", "expected"),
    [
        ("localhost:50051", ("localhost", 50051)),
        ("drvs-server:1", ("drvs-server", 1)),
        ("camera-1.office.example.com:65535", ("camera-1.office.example.com", 65535)),
        ("127.0.0.1:9", ("127.0.0.1", 9)),
        ("10.20.30.40:50070", ("10.20.30.40", 50070)),
        ("[::1]:50051", ("::1", 50051)),
        ("[fe80::1:2]:8080", ("fe80::1:2", 8080)),
        ("[2001:db8::7]:443", ("2001:db8::7", 443)),
    ],
)
def test_parse_valid(address: str, expected: tuple[str, int]) -> None:
    assert parse_address(address) == expected


@pytest.mark.parametrize(
    ("address", "message"),
    [
        ("", r"^address: empty; expected host:port"),
        ("localhost", r"^address: 'localhost' is not host:port"),
        (":50051", r"^address: ':50051' is not host:port"),
        ("localhost:", r"^address: port '' is not a number"),
        ("localhost:0", r"^address: port 0 is out of range"),
        ("localhost:70000", r"^address: port 70000 is out of range"),
        ("localhost:65536", r"^address: port 65536 is out of range"),
        ("localhost:-1", r"^address: port '-1' is not a number"),
        ("localhost:http", r"^address: port 'http' is not a number"),
        ("localhost: 80", r"^address: port ' 80' is not a number"),
        ("localhost:80 ", r"^address: port '80 ' is not a number"),
        ("bad host:80", r"^address: 'bad host' is not a valid host name or IPv4 address"),
        (" localhost:80", r"^address: ' localhost' is not a valid host"),
        ("my host name:80", r"^address: 'my host name' is not a valid host"),
        ("host_name:80", r"^address: 'host_name' is not a valid host"),
        ("-host:80", r"^address: '-host' is not a valid host"),
        ("host..name:80", r"^address: 'host..name' is not a valid host"),
        ("::1:80", r"^address: '::1' is not a valid host"),
        ("[::1]", r"^address: '\[::1\]' is not \[ipv6\]:port"),
        ("[::1]80", r"^address: '\[::1\]80' is not \[ipv6\]:port"),
        ("[::1:80", r"^address: '\[::1:80' is not \[ipv6\]:port"),
        ("[not-v6]:80", r"^address: 'not-v6' is not an IPv6 address"),
        ("[::1]:0", r"^address: port 0 is out of range"),
        ("[::1]:99999", r"^address: port 99999 is out of range"),
    ],
)
def test_parse_invalid(address: str, message: str) -> None:
    with pytest.raises(InvalidArgument, match=message):
        parse_address(address)


def test_the_field_name_is_in_the_message() -> None:
    with pytest.raises(InvalidArgument, match=r"^callback_address: 'robot' is not host:port"):
        parse_address("robot", "callback_address")


def test_port_zero_only_when_allowed() -> None:
    assert parse_address("127.0.0.1:0", allow_port_zero=True) == ("127.0.0.1", 0)
    assert parse_address("[::1]:0", allow_port_zero=True) == ("::1", 0)
    with pytest.raises(InvalidArgument, match=r"^address: port 0 is out of range"):
        parse_address("127.0.0.1:0")
    with pytest.raises(InvalidArgument, match=r"^address: port 70000 is out of range"):
        parse_address("127.0.0.1:70000", allow_port_zero=True)


@pytest.mark.parametrize(
    "address",
    [
        "localhost:\u00b2",  # SUPERSCRIPT TWO: str.isdigit() is true, int() refuses it
        "localhost:\uff18\uff10",  # FULLWIDTH DIGIT EIGHT, ZERO: not an ASCII port number
        "localhost:\u0668\u0660",  # ARABIC-INDIC DIGIT EIGHT, ZERO
    ],
)
def test_port_must_be_ascii_digits(address: str) -> None:
    with pytest.raises(InvalidArgument, match=r"^address: port .* is not a number"):
        parse_address(address)


def test_host_with_a_trailing_newline_is_refused() -> None:
    with pytest.raises(InvalidArgument, match=r"^address: 'localhost\\n' is not a valid host"):
        parse_address("localhost\n:80")


@pytest.mark.parametrize(
    ("host", "port"),
    [("localhost", 50051), ("127.0.0.1", 9), ("::1", 8080), ("2001:db8::7", 443)],
)
def test_format_address_round_trips(host: str, port: int) -> None:
    assert parse_address(format_address(host, port)) == (host, port)
