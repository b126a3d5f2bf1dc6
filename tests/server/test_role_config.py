"""Each role's settings are validated once: the Python constructor (DrvsServer, CameraNode), the
command line and the DRVS_* environment refuse a bad value by the same check, with the same
message. The command lines run as real processes: exit code 2, no traceback."""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any

import pytest

from drvs.camera.node import CameraNode
from drvs.camera.source import VideoSource
from drvs.core.errors import InvalidArgument
from drvs.core.geometry import homography_from_pose
from drvs.server import DrvsServer
from drvs.server.config import ServerConfig
from drvs.tools.launch import ManagedProcess

CAMERA_ARGS = ("--id", "cam1", "--source", "x.avi", "--homography", "h.yaml")


def refusal(make: Callable[[], Any]) -> str:
    """The message of the InvalidArgument that `make()` must raise."""
    with pytest.raises(InvalidArgument) as err:
        make()
    return str(err.value)


async def usage_error(command: str, *args: str, env: dict[str, str] | None = None) -> str:
    """Run a CLI that must refuse its input: exit code 2, no traceback; its error message."""
    environ = {k: v for k, v in os.environ.items() if not k.startswith("DRVS_")} | (env or {})
    proc = await ManagedProcess.entry_point(command, command, *args, env=environ).start()
    try:
        code = await proc.wait(timeout=60)
    finally:
        await proc.stop()
    output = proc.output()
    assert code == 2 and "Traceback" not in output, output
    prefix = f"{command}: error: "
    assert proc.lines and proc.lines[-1].startswith(prefix), output
    return proc.lines[-1][len(prefix) :]


@pytest.mark.parametrize(
    ("keywords", "args", "env"),
    [
        ({"forward_timeout_s": 0}, ("--forward-timeout", "0"), {}),
        ({"lease_ttl_s": 0}, (), {"DRVS_LEASE_TTL": "0"}),
        ({"max_queued_forwards": 0}, ("--max-queued-forwards", "0"), {}),
    ],
    ids=["forward-timeout", "DRVS_LEASE_TTL", "max-queued-forwards"],
)
async def test_the_server_constructor_and_drvs_server_refuse_alike(
    keywords: dict[str, Any], args: tuple[str, ...], env: dict[str, str]
) -> None:
    message = refusal(lambda: DrvsServer("127.0.0.1:0", **keywords))
    [name] = keywords
    assert message.startswith(f"{name} (") and " must be in " in message, message
    assert await usage_error("drvs-server", "--listen", "127.0.0.1:0", *args, env=env) == message


async def test_the_camera_constructor_and_drvs_camera_refuse_alike() -> None:
    """The same check and wording; the CLI adds where the value came from."""
    h = homography_from_pose((0.0, 0.0, 3.0), 90.0, 40.0, 60.0, (640, 480))
    message = refusal(lambda: CameraNode("cam1", VideoSource("x.avi"), h, "127.0.0.1:1", max_continuous=0))
    assert message == "max_continuous: 0 must be a whole number from 1 to 1000000"
    rest = message[len("max_continuous") :]
    flag = await usage_error("drvs-camera", *CAMERA_ARGS, "--max-continuous", "0")
    assert flag == f"max_continuous (from --max-continuous){rest}"
    variable = await usage_error("drvs-camera", *CAMERA_ARGS, env={"DRVS_CAMERA_MAX_CONTINUOUS": "0"})
    assert variable == f"max_continuous (from DRVS_CAMERA_MAX_CONTINUOUS){rest}"


def test_server_config_takes_a_flag_over_its_variable_over_the_default() -> None:
    assert ServerConfig.load({}, {}).lease_ttl_s == ServerConfig().lease_ttl_s
    assert ServerConfig.load({}, {"DRVS_LEASE_TTL": "7"}).lease_ttl_s == 7.0
    assert ServerConfig.load({"lease_ttl_s": 3.0}, {"DRVS_LEASE_TTL": "7"}).lease_ttl_s == 3.0
    assert ServerConfig.load({"lease_ttl_s": None}, {"DRVS_LEASE_TTL": "7"}).lease_ttl_s == 7.0
    assert ServerConfig.load({}, {"DRVS_TRUST_NETWORK": "yes"}).trust_network is True
    config = ServerConfig.load({"listen": "127.0.0.1:0"}, {"DRVS_SERVER_LISTEN": "127.0.0.1:9"})
    assert config.listen == "127.0.0.1:0"
    # The config's limits are what the server enforces.
    server = DrvsServer(config=ServerConfig(rate_limit_hz=3, max_continuous=4, max_forward_bytes_per_s=5))
    assert (server.limits.rate_hz, server.limits.burst, server.limits.max_active) == (3, 6, 4)
    assert server.limits.forward_bytes_per_s == 5


def test_the_server_constructor_refuses_what_only_it_takes() -> None:
    assert refusal(lambda: DrvsServer(default_max_range_m=150)) == (
        "default_max_range_m: 150 m must be in (0, max_fov_range_m 100 m]"
    )
    assert DrvsServer(default_max_range_m=150, max_fov_range_m=200).default_max_range_m == 150
    assert refusal(lambda: DrvsServer(config=ServerConfig(), forward_timeout_s=5)) == (
        "config: give the settings either as a ServerConfig or as keywords, not both"
    )


@pytest.mark.parametrize(
    ("keywords", "message"),
    [
        ({"listen": 50051}, "listen (--listen, DRVS_SERVER_LISTEN): expected a string, got int"),
        ({"registry": 5}, "registry (--registry, DRVS_REGISTRY): expected a string, got int"),
        ({"advertise": 7}, "advertise (--advertise, DRVS_SERVER_ADVERTISE): expected a string, got int"),
        ({"allow_callback": "10.0.0.0/8"}, "allow_callback (--allow-callback): expected a list of networks, got str"),
        ({"allow_callback": [8]}, "allow_callback (--allow-callback): expected a string such as '10.0.0.0/8', got int"),
    ],
)
def test_the_server_constructor_refuses_a_setting_of_the_wrong_type_naming_it(
    keywords: dict[str, Any], message: str
) -> None:
    """DrvsServer(...) from Python: a number for a text setting, or one network as a string where
    a list is asked for, is refused naming the setting (an AttributeError, a TypeError or 'listen:
    empty' before, or the string read as one network a character)."""
    assert refusal(lambda: DrvsServer(**keywords)) == message
