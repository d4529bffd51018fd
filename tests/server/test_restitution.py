"""Each point's restitution, from the engine to the face route: Box2D holds a point that closes
faster than 1 m/s at a bounce (its restitution times that speed), so the route solves and prices
such a step with it (StepRequest.point_restitution, deepcontact.faces.prepare_route)."""

from __future__ import annotations

import inspect
import shutil

import Box2D
import numpy as np
import pytest

from deepcontact import wire
from simclient.engine import Engine
from tests.conftest import shipped_model_files


def boxes_dropped_on_bouncy_ground(restitution: float = 0.4) -> Box2D.b2World:
    """Five boxes (restitution 0.1) falling onto a ground edge of `restitution` from 1.5 m: they
    land at about 5 m/s, closing faster than Box2D's 1 m/s threshold."""
    world = Box2D.b2World(gravity=(0.0, -9.8))
    world.CreateStaticBody().CreateEdgeFixture(vertices=[(-20.0, 0.0), (20.0, 0.0)], friction=0.5,
                                               restitution=restitution)
    for x in np.linspace(-4.0, 4.0, 5):
        box = world.CreateDynamicBody(position=(float(x), 2.0))
        box.CreatePolygonFixture(box=(0.5, 0.5), density=1.0, friction=0.5, restitution=0.1)
    return world


def test_a_points_restitution_is_the_larger_of_its_two_fixtures():
    engine = Engine(boxes_dropped_on_bouncy_ground(0.4))
    while engine.collide() == 0:
        engine.solve()
    points = engine.contacts()
    np.testing.assert_allclose(engine.point_restitution(points), 0.4)  # max(0.4, 0.1), as b2MixRestitution


def test_a_request_carries_each_points_restitution_only_where_one_has_any():
    engine = Engine(boxes_dropped_on_bouncy_ground())
    while engine.collide() == 0:
        engine.solve()
    bodies, points = engine.bodies(), engine.contacts()
    sent = wire.encode_step(0, "zoo", bodies, points, restitution=engine.point_restitution(points))
    np.testing.assert_allclose(wire.decode_restitution(sent), 0.4)
    assert not wire.encode_step(0, "zoo", bodies, points, restitution=np.zeros(len(points))).point_restitution
    assert wire.decode_restitution(wire.encode_step(0, "zoo", bodies, points)) is None  # an older client
    sent.point_restitution = np.full(len(points), -0.1, np.float32).tobytes()
    with pytest.raises(wire.WireError, match="point_restitution: holds negative values"):
        wire.decode_restitution(sent)
    sent.point_restitution = np.zeros(len(points) + 1, np.float32).tobytes()
    with pytest.raises(wire.WireError, match="point_restitution"):
        wire.decode_restitution(sent)


def test_a_user_world_served_over_the_wire_hands_the_zoo_route_each_points_restitution(tmp_path, monkeypatch):
    # The shipped default serves a world it was not trained on by its zoo route; at the landing the
    # route is handed the restitution the simulation sent, 0.4 at every point.
    from server.face_route import FaceRoutePredictor
    from server.serve import Server
    from simclient.session import WarmStartSession

    for path in shipped_model_files(["default"]):
        shutil.copy(path, tmp_path)
    handed = []
    route = FaceRoutePredictor._route

    def recorded(self, *args, **kwargs):
        given = inspect.signature(route).bind(self, *args, **kwargs).arguments.get("restitution")
        handed.append((self.name, given))
        return route(self, *args, **kwargs)

    monkeypatch.setattr(FaceRoutePredictor, "_route", recorded)
    srv = Server(models=tmp_path, bind="127.0.0.1:0").start()
    try:
        with WarmStartSession(boxes_dropped_on_bouncy_ground(), srv.address, model="default", deadline_ms=5000,
                              guard=False) as session:
            for _ in range(60):
                session.step(1.0 / 60.0, 500, 3)
            assert session.summary()["fallback_steps"] == 0
    finally:
        srv.stop()
    given = [r for name, r in handed if name == "zoo" and r is not None]
    assert given and all(np.allclose(r, 0.4) for r in given)
