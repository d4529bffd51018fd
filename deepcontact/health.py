"""`deepcontact health --server HOST:PORT`: exit 0 if the warm-start service
reports SERVING (for container health checks and scripts). With --tls-ca,
--tls-cert and --tls-key it dials a TLS server, presenting a client certificate
to one that requires them (deepcontact serve --tls-client-ca)."""

from __future__ import annotations

import argparse
import sys

import grpc
from grpc_health.v1 import health_pb2, health_pb2_grpc

from deepcontact import tls


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--server", default="127.0.0.1:50051", help="gRPC target (default 127.0.0.1:50051)")
    parser.add_argument("--timeout", type=float, default=3.0, help="seconds (default 3)")
    tls.add_client_arguments(parser)


def run(args: argparse.Namespace) -> int:
    try:
        credentials = tls.credentials_from_args(args)
    except ValueError as exc:  # a certificate without its key, a file that cannot be read
        print(f"deepcontact health: {exc}", file=sys.stderr)
        return 2
    try:
        with _channel(args.server, credentials) as channel:
            status = health_pb2_grpc.HealthStub(channel).Check(
                health_pb2.HealthCheckRequest(service="deepcontact.v1.WarmStart"), timeout=args.timeout).status
    except grpc.RpcError as err:
        print(f"{args.server}: {err.code().name}", file=sys.stderr)
        return 1
    name = health_pb2.HealthCheckResponse.ServingStatus.Name(status)
    print(f"{args.server}: {name}")
    return 0 if status == health_pb2.HealthCheckResponse.SERVING else 1


def _channel(target: str, credentials: grpc.ChannelCredentials | None) -> grpc.Channel:
    """A TLS channel with credentials, else a plaintext one."""
    return grpc.secure_channel(target, credentials) if credentials is not None else grpc.insecure_channel(target)
