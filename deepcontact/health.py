"""`deepcontact health --server HOST:PORT`: exit 0 if the warm-start service
reports SERVING (for container health checks and scripts)."""

from __future__ import annotations

import argparse
import sys

import grpc
from grpc_health.v1 import health_pb2, health_pb2_grpc


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--server", default="127.0.0.1:50051", help="gRPC target (default 127.0.0.1:50051)")
    parser.add_argument("--timeout", type=float, default=3.0, help="seconds (default 3)")


def run(args: argparse.Namespace) -> int:
    try:
        with grpc.insecure_channel(args.server) as channel:
            status = health_pb2_grpc.HealthStub(channel).Check(
                health_pb2.HealthCheckRequest(service="deepcontact.v1.WarmStart"), timeout=args.timeout).status
    except grpc.RpcError as err:
        print(f"{args.server}: {err.code().name}", file=sys.stderr)
        return 1
    name = health_pb2.HealthCheckResponse.ServingStatus.Name(status)
    print(f"{args.server}: {name}")
    return 0 if status == health_pb2.HealthCheckResponse.SERVING else 1
