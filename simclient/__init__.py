"""Simulation side: scenes and users' worlds, the patched-engine wrapper, warm starts, the
client, and the session API for a world you built:

    from simclient import WarmStartSession

Importing this package checks for the patched Box2D at once (see engine.py).
"""

from simclient import engine as _engine  # noqa: F401  (fails fast on a stock Box2D)


def __getattr__(name: str):
    # The session pulls in gRPC and the client: only when it is asked for.
    if name in ("WarmStartSession", "StepResult"):
        from simclient import session

        return getattr(session, name)
    raise AttributeError(f"module 'simclient' has no attribute {name!r}")
