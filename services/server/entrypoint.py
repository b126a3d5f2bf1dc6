"""Server container entrypoint: `drvs-server` with the container's flags and DRVS_* settings.

With DRVS_REGISTRY unset and DRVS_REGISTRY_IF_PRESENT=HOST:PORT set (compose.yaml does), the
registry is etcd://HOST:PORT when HOST resolves (compose's ha profile runs an `etcd` service on
the project network), and this server's memory otherwise (the plain office has no etcd). Then this
process becomes drvs-server (exec), which handles SIGTERM itself.
"""

from __future__ import annotations

import os
import socket
import sys

DRVS_SERVER = "drvs-server"


def main() -> None:
    argv = sys.argv[1:]
    wanted = os.environ.get("DRVS_REGISTRY_IF_PRESENT", "")
    if wanted and not os.environ.get("DRVS_REGISTRY") and not any(a.startswith("--registry") for a in argv):
        host = wanted.rsplit(":", 1)[0]
        try:
            socket.getaddrinfo(host, None)
        except OSError:
            print(f"server: no {host} on this network: the registry stays in this server's memory", flush=True)
        else:
            os.environ["DRVS_REGISTRY"] = f"etcd://{wanted}"
            print(f"server: the registry is shared in etcd://{wanted}", flush=True)
    os.execvp(DRVS_SERVER, [DRVS_SERVER, *argv])


if __name__ == "__main__":
    main()
