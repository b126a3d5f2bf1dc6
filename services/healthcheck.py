"""Container health check: ask a DRVS role's gRPC health service (grpc.health.v1) whether it serves.

    python /opt/drvs-services/healthcheck.py [HOST:PORT] [SERVICE]

HOST:PORT defaults to $DRVS_HEALTH_ADDRESS or 127.0.0.1:50051; SERVICE to "" (the whole process).
Exit 0 when the answer is SERVING, 1 otherwise (NOT_SERVING, unreachable, timeout), as Docker wants.
"""

from __future__ import annotations

import os
import sys

import grpc
from grpc_health.v1 import health_pb2, health_pb2_grpc


def main(argv: list[str]) -> int:
    address = argv[1] if len(argv) > 1 else os.environ.get("DRVS_HEALTH_ADDRESS", "127.0.0.1:50051")
    service = argv[2] if len(argv) > 2 else ""
    try:
        with grpc.insecure_channel(address) as channel:
            reply = health_pb2_grpc.HealthStub(channel).Check(
                health_pb2.HealthCheckRequest(service=service), timeout=2.0
            )
    except grpc.RpcError as exc:
        print(f"{address}: {exc.code().name}: {exc.details()}", file=sys.stderr)
        return 1
    status = health_pb2.HealthCheckResponse.ServingStatus.Name(reply.status)
    print(f"{address}: {status}")
    return 0 if reply.status == health_pb2.HealthCheckResponse.SERVING else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv))
