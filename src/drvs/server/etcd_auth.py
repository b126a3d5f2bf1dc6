"""etcd's own access control for DRVS: only DRVS servers may read or write the registry's keys.

etcd started with `--client-cert-auth` takes a client certificate's common name as the user name
once authentication is on. This sets that up through etcd's auth API (what `etcdctl user add`,
`role add`, `role grant-permission`, `user grant-role` and `auth enable` do):

- a role, `drvs-server`, that may read and write the keys under the registry's prefix (`/drvs/v1/`);
- one user per server, named as the common name of that server's certificate for etcd (no
  password: the certificate is the credential), holding that role;
- `root` (etcd requires it before auth goes on), whose certificate (common name `root`,
  `drvs-certs --etcd`) is then the only way to change users and roles;
- authentication on.

Any other certificate from the same CA (a robot's, a camera's) names no user etcd knows: etcd
refuses it, for reads and for writes. Run it once, with the root certificate, against a cluster
whose authentication is still off (or on: root may change users); running it again adds what is
missing and changes nothing else:

    python -m drvs.server.etcd_auth --endpoints etcd://10.0.0.5:2379 --ca ca.pem \\
        --cert etcd-root.pem --key etcd-root-key.pem --user server
"""

from __future__ import annotations

import argparse
import asyncio
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import grpc
from grpc import aio

from drvs.core.errors import InvalidArgument, Unavailable
from drvs.core.model import check_id
from drvs.server.etcd import Endpoints, EtcdClient, _prefix_end

#: The etcd role DRVS servers hold, and the prefix it opens (drvs.server.shared.ROOT).
SERVER_ROLE = "drvs-server"
PREFIX = b"/drvs/v1/"
ROOT_USER = "root"


async def _ignoring_exists(call: Any, request: Any, metadata: Any) -> None:
    try:
        await call(request, metadata=metadata)
    except aio.AioRpcError as exc:
        if "already exists" not in (exc.details() or ""):
            raise


async def enable(client: EtcdClient, users: Sequence[str], prefix: bytes = PREFIX) -> None:
    """Give each of `users` (server certificates' common names) read and write access to `prefix`
    and nothing else, make `root`, and turn authentication on. Unavailable naming what failed."""
    if not users:
        raise InvalidArgument("users: name at least one server (its certificate's common name)")
    for user in users:
        check_id(user, "user")
        if user == ROOT_USER:
            raise InvalidArgument("users: 'root' administers etcd; a DRVS server has a user of its own")
    rpc = client._rpc
    stub = rpc.AuthStub(client._channel)
    meta = client._metadata
    no_password = rpc.UserAddOptions(no_password=True)
    try:
        await _ignoring_exists(stub.RoleAdd, rpc.AuthRoleAddRequest(name=SERVER_ROLE), meta)
        permission = rpc.Permission(permType=rpc.Permission.READWRITE, key=prefix, range_end=_prefix_end(prefix))
        await stub.RoleGrantPermission(
            rpc.AuthRoleGrantPermissionRequest(name=SERVER_ROLE, perm=permission), metadata=meta
        )
        for user in users:
            await _ignoring_exists(stub.UserAdd, rpc.AuthUserAddRequest(name=user, options=no_password), meta)
            await stub.UserGrantRole(rpc.AuthUserGrantRoleRequest(user=user, role=SERVER_ROLE), metadata=meta)
        await _ignoring_exists(stub.UserAdd, rpc.AuthUserAddRequest(name=ROOT_USER, options=no_password), meta)
        await stub.UserGrantRole(rpc.AuthUserGrantRoleRequest(user=ROOT_USER, role=ROOT_USER), metadata=meta)
        await stub.AuthEnable(rpc.AuthEnableRequest(), metadata=meta)  # on already: no change
    except aio.AioRpcError as exc:
        raise Unavailable(f"etcd {client.endpoints}: auth setup: {exc.code().name} {exc.details()}") from None


async def _main(args: argparse.Namespace) -> None:
    credentials = grpc.ssl_channel_credentials(
        root_certificates=args.ca.read_bytes(),
        private_key=args.key.read_bytes(),
        certificate_chain=args.cert.read_bytes(),
    )
    async with EtcdClient(Endpoints.parse(args.endpoints, "endpoints"), credentials=credentials) as client:
        await enable(client, args.user)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m drvs.server.etcd_auth", description=__doc__, formatter_class=argparse.RawTextHelpFormatter
    )
    p.add_argument("--endpoints", required=True, metavar="etcd://HOST:PORT[,...]", help="the etcd cluster")
    p.add_argument("--ca", type=Path, required=True, help="the CA etcd's certificate is checked against")
    p.add_argument("--cert", type=Path, required=True, help="etcd's root certificate (common name root)")
    p.add_argument("--key", type=Path, required=True, help="its key")
    p.add_argument(
        "--user", action="append", default=[], required=True, help="a DRVS server's etcd user: the common name of "
        "its --etcd-cert (repeatable)",
    )  # fmt: skip
    args = p.parse_args(argv)
    try:
        asyncio.run(_main(args))
    except (InvalidArgument, Unavailable, OSError) as exc:
        print(f"drvs.server.etcd_auth: {exc}", file=sys.stderr)
        return 2
    print(f"etcd {args.endpoints}: authentication on; servers {', '.join(args.user)} may use {PREFIX.decode()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
