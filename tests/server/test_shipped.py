"""models/ holds what is shipped and served, each card saying what it is."""

from __future__ import annotations

import json
from pathlib import Path

from server.process import ServerProcess
from simclient.client import WarmStartClient

SHIPPED = Path(__file__).parents[2] / "models"


def test_the_served_folder_holds_the_shipped_models_only():
    files = sorted(p.name for p in SHIPPED.iterdir())
    assert len(files) <= 20
    cards = {p.stem: json.loads(p.read_text()) for p in SHIPPED.glob("*.json")}
    assert {"default", "contact-modes", "contact-modes-zoo", "zoo", "contact-graph", "pressure"} <= set(cards)
    # The default's route, then the zoo's route where contact-modes does not know the world or its
    # solve misses its labels, then the graph network.
    assert cards["default"]["alias_of"] == "contact-modes"
    assert cards["default"]["face"]["fallback"] == "zoo"
    assert cards["zoo"]["alias_of"] == "contact-modes-zoo"
    assert cards["zoo"]["face"]["fallback"] == "contact-graph"
    for name, card in cards.items():
        assert card.get("description") and "\n" not in card["description"], name


def test_serve_lists_each_shipped_model_with_its_line():
    with ServerProcess(SHIPPED, local_socket=True) as server, WarmStartClient(server.address) as client:
        models = {m.name: m for m in client.list_models()}
    assert {"default", "zoo", "contact-modes", "contact-modes-zoo", "contact-graph", "pressure", "zero"} <= set(models)
    assert models["default"].description.startswith("the face route")
    assert all(m.description for m in models.values())
