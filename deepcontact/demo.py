"""`deepcontact demo`: the main job (server, simulations, results table).

Not yet available: it lands with the server and the client (issues 6, 7, 9).
"""

from __future__ import annotations

import argparse
import sys


def add_arguments(parser: argparse.ArgumentParser) -> None:
    pass


def run(args: argparse.Namespace) -> int:
    print(
        "deepcontact demo: not yet available. The patched engine is built and tested "
        "(`make test`); try `deepcontact bench engine` meanwhile.",
        file=sys.stderr,
    )
    return 0
