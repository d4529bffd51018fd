"""Prometheus metrics of the warm-start service.

Exposed over HTTP by `deepcontact serve --metrics-port PORT` at /metrics:
    deepcontact_steps_total{model}           steps answered
    deepcontact_errors_total{code}           requests rejected, by gRPC status
    deepcontact_stage_seconds{stage}         decode, each stage a predictor runs (server.predictors.STAGES:
                                             p2g, features, inference, g2p, solve, admit), total
    deepcontact_idle_streams_ended_total     streams the server ended after --stream-idle-s without a message
    deepcontact_served_by_total{model,served_by}  steps a model answered with another card's answer
                                             (a face card's fallback: too large, labels missed, or late)
"""

from __future__ import annotations

from prometheus_client import Counter, Histogram, start_http_server

from server.predictors import STAGES

STEPS = Counter("deepcontact_steps_total", "Steps answered", ["model"])
ERRORS = Counter("deepcontact_errors_total", "Requests rejected, by gRPC status code", ["code"])
SERVED_BY = Counter("deepcontact_served_by_total", "Steps a model answered with another card's answer",
                    ["model", "served_by"])
SHED = Counter("deepcontact_shed_total", "Steps refused (RESOURCE_EXHAUSTED) because their budget was spent before any "
               "work began", ["model"])
IDLE_ENDED = Counter("deepcontact_idle_streams_ended", "Streams ended by the server after --stream-idle-s without a message")
STAGE = Histogram(
    "deepcontact_stage_seconds", "Server-side time per stage of a step", ["stage"],
    buckets=(25e-6, 50e-6, 100e-6, 200e-6, 400e-6, 800e-6, 1.6e-3, 3.2e-3, 6.4e-3, 12.8e-3, 25.6e-3, 51.2e-3, 0.1),
)
_STAGES = {name: STAGE.labels(stage=name) for name in ("decode", *STAGES, "total")}


def observe_step(model: str, decode_s: float, stages: dict[str, float], total_s: float) -> None:
    STEPS.labels(model=model).inc()
    _STAGES["decode"].observe(decode_s)
    for name, seconds in stages.items():
        _STAGES[name].observe(seconds)
    _STAGES["total"].observe(total_s)


def serve_metrics(port: int, host: str = "127.0.0.1") -> None:
    """Start the /metrics HTTP endpoint in a daemon thread."""
    start_http_server(port, addr=host)
