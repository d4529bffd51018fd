"""lab.shared_directions: the free directions of a zoo pyramid's step seen densely, against the
compiled route's solve on them."""

from __future__ import annotations

from lab.shared_directions import report


def test_a_zoo_pyramids_step_has_free_directions_several_bodies_share_and_the_route_solves_it_in_the_bodies_space():
    row = report(901, 30, calls=1)
    assert row["shared"] > 10 and row["own"] > 0  # rows of boxes sliding together, and bodies free alone
    assert row["product"] < 1e-9  # R Q (Q^T G Q)^-1 (Q^T K Q)^-1 Q^T L^T is the pseudo-inverse here
    assert row["in_bodies"] and row["against_dual"] < 1e-8
