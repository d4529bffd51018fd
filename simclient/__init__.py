"""Simulation side: scenes, the patched-engine wrapper, warm starts, the client.

Importing this package checks for the patched Box2D at once (see engine.py).
"""

from simclient import engine as _engine  # noqa: F401  (fails fast on a stock Box2D)
