"""The `deepcontact lab` commands: the research instruments (lab/README.md).

`simulate` and `iterations` are the product's `simulate` and `bench iterations` (the same
modules, the same flags), run with the lab's warm starts registered: importing this table
imports `lab`, which registers them. The others are the lab's own benches.
"""

from __future__ import annotations

from deepcontact.cli import Command

COMMANDS = [
    Command(("simulate",), "simclient.simulate",
            "`deepcontact simulate` with the lab's warm starts too (oracle:, probes, composites)"),
    Command(("iterations",), "bench.iterations",
            "`deepcontact bench iterations` with the lab's warm starts too (price:, shadow:, pick:, oracle:, ...)"),
    Command(("admission",), "lab.admission",
            "what admitting a motion (nearest_admissible) costs a step, beside Box2D's solve"),
    Command(("admission-carry",), "lab.admission_carry",
            "where should a step's admission begin along a stream? cold, or where its points' stopped the step before"),
    Command(("corrections",), "lab.corrections",
            "a served model's corrections against the solver's, by size: where it errs"),
    Command(("face-solve",), "lab.face_solve",
            "the face route's solve by step size: its system, the dual solve against gelsy, the admission"),
    Command(("faces",), "lab.faces",
            "a served model's answer read as an active set (open, sticks, slides): how many labels a step are wrong"),
    Command(("generate",), "lab.generate", "what recording simulations costs over running them"),
    Command(("graph-size",), "lab.graph_size", "a contact-graph model's inference against the step's points and bodies"),
    Command(("joint-route",), "lab.joint_route",
            "would the route pay on jointed worlds with the joints in its problem? priced on Box2D's states"),
    Command(("route-ceiling",), "lab.route_ceiling",
            "how far can the face route take a world with the oracle's own labels? priced on Box2D's states"),
    Command(("jointed-points",), "lab.jointed_points",
            "on a world with joints, do the points at jointed bodies or the rest keep the default from the solution?"),
    Command(("joint-copy",), "lab.joint_copy",
            "does the server's copy of a step count Box2D's sweeps, with the joints (revolute, weld, prismatic) in it and without?"),
    Command(("joint-start",), "lab.joint_start",
            "closed loop (or --on-builtin, on Box2D's states) on revolute joints: would a reply that carried the joints' impulses too buy iterations?"),
    Command(("joints-price",), "lab.joints_price",
            "does declining at jointed points pay? a model priced on Box2D's states with the joints sent and withheld"),
    Command(("inference",), "lab.inference",
            "ONNX Runtime levers on a grid model's inference: session options, int8, cropped grids"),
    Command(("label-reuse",), "lab.label_reuse",
            "can a stream keep the classifier's labels across steps? the route on held and fresh labels"),
    Command(("order",), "lab.order",
            "does the order of the solver's sweep choose its answer? a Gauss-Seidel replica in several orders"),
    Command(("route-stages",), "lab.route_stages",
            "where a served model's step goes on any world, by its size: each stage's median, in process"),
    Command(("spread",), "lab.closed_loop_spread",
            "how far a closed loop moves when nothing that matters changes: Builtin against itself perturbed"),
    Command(("step-gate",), "lab.step_gate",
            "a per-step gate between a model's warm start and Box2D's, fitted on some seeds, priced on others"),
    Command(("surrogate",), "lab.surrogate",
            "does the training loss's score of a step follow the iterations a model saves there?"),
]
