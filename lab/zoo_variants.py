"""A model folder with the zoo's variants beside the shipped models, for pricing them on the same
states (docs/research/2026-12-06-a-zoo-of-worlds.md):

    python -m lab.zoo_variants runs/zoo-variants
    deepcontact lab iterations --world simclient.zoo:stack --seeds 850-854 --no-guard \
        --models runs/zoo-variants --warm-starts builtin,price:server:default+server:zoo+server:zoo-first

Beside models/ (whose `default` and `zoo` are the shipped ones) it writes, each a card over a
network of the research store (lab/models); every `zoo-...` variant changes the zoo route as it
was shipped until its check counted sweeps to the stopping rule (ZOO_FACE, `zoo-before`), the
`default-...` ones the shipped default's own route, falling back to `zoo-before` unless they
name another:

    default-bf      the default with Box2D's start in place of its fallback (no `fallback`)
    default-graph   the default falling back to contact-graph directly, as until 2026-12-06
    zoo-first       the zoo route on the first run of the zoo's recipe (zoo-first-modes)
    zoo-bf          the zoo route with Box2D's start in place of its fallback
    zoo-always      the zoo route on every step: no max_residual, max_points 5,000
    zoo-r0.6        the zoo route with max_residual 0.6 in place of 0.3
    default-r0.6    the default with max_residual 0.6 in place of 0.3 (its zoo route's still 0.3)
    default-first   the default falling back to zoo-first
    zoo500          the zoo route on the zoo's recipe trained on 500 simulations of each class in
                    place of 200 (zoo500-modes: graph-labels-scaled-zoo500-r12-e4)
    default-zoo500  the default falling back to zoo500
    zoo-unchecked   the zoo route without against_builtin: its answer served without comparing it
                    with Box2D's start, as until 2026-12-06
    default-unchecked the default falling back to zoo-unchecked
    zoo-r200        the zoo route with 200 admission rounds in place of 50
    zoo-before      the zoo route as ZOO_FACE has it (default-zoo-before the default falling back to it)
    zoo-ungated     the zoo route with no max_residual (its fallback kept, unlike zoo-always);
                    zoo-ungated-r200 the same in 200 rounds, zoo-ungated-r200-unchecked that
                    without against_builtin (docs/research/2026-12-06-labels-from-box2ds-start.md)
    zoo-checkK      the zoo route checked against Box2D's start by K of the solver's sweeps in
                    place of 12, for K in CHECK_SWEEPS; zoo-ungated-r200-checkK the same for
                    zoo-ungated-r200; default-zoo-checkK and default-zoo-ungated-r200-checkK the
                    default falling back to each
    zoo-resR-r200-check200  the zoo route in 200 rounds, checked by 200 sweeps, its max_residual
                    R / 10 (for R in GATES); default-zoo-resR-r200-check200 the default falling back to it
    ...-stop        each check by sweeps above counting the sweeps each start takes to the client's
                    stopping rule (face check_stop): zoo-stop (the shipped zoo route so),
                    zoo-ungated-r200-checkK-stop for K in STOP_SWEEPS, default-zoo-... the default
                    falling back to each; default-stop the default's own route so (its fallback
                    zoo-before), default-stop-zoo-ungated-r200-checkK-stop both;
                    zoo-ungated-rN-check200-stop the same in N rounds for N in STOP_ROUNDS,
                    zoo-resR-rN-check200-stop those gated at R / 10 for R in STOP_GATES
                    (docs/research/2026-12-06-the-zoo-checks-sweeps.md)
    zoo-s7e6        the zoo route as shipped (models/zoo.json's face, not ZOO_FACE) on the shipped
                    zoo classifier trained six more epochs (s7e6-modes:
                    graph-labels-scaled-zoo-r12-e4-s7-e6); default-s7e6 the shipped default
                    falling back to it; zoo-s7e6-s9e6 and default-s7e6-s9e6 the same on that network
                    trained six epochs more (s7e6-s9e6-modes: graph-labels-scaled-zoo-r12-e4-s7-e6-s9-e6)
                    (docs/research/2026-12-07-the-zoo-classifier-trained-on.md)
    zoo-island      the zoo route as shipped (models/zoo.json's face) checking each island of a
                    step on its own and serving each the start that stops it sooner (face
                    by_island); default-island the shipped default falling back to it; zoo-whole
                    and default-whole the same without by_island (nor repairs), whatever the
                    shipped zoo route does (docs/research/2026-12-07-island-by-island.md)
    zoo-bounce      the zoo route as shipped (models/zoo.json's face), each point that closes faster
                    than 1 m/s held at its restitution's bounce in its solve and its check, as Box2D's
                    solver holds it (face restitution); default-bounce the shipped default falling
                    back to it; zoo-bounceless and default-bounceless the same with every point held
                    at rest, as until then (docs/research/2026-12-07-the-zoo-pyramids-ceiling.md)
    default-own-repairK  the shipped default with its own route checked island by island by the
                    sweeps each start takes to the client's stopping rule, up to 200 (check_stop,
                    by_island), and its answer repaired up to K times, for K in OWN_REPAIRS
                    (docs/research/2026-12-08-repaired-labels.md, "The thesis world")
    default-own-stopK  the shipped default with its own route checked by the sweeps each start
                    takes to the client's stopping rule, up to K (check_stop, check_sweeps K; the
                    shipped one compares the changes at its twelfth sweep), for K in OWN_STOP_SWEEPS
                    (docs/research/2026-12-07-island-by-island.md, "The thesis world's check")

    zoo-work-W      the zoo route as shipped until 2026-12-07's last change (LARGE_BEFORE) with its
                    check playing no more than W / points sweeps from each start (face check_work W)
                    for W in CHECK_WORK; zoo-work-none that route as it was (200 sweeps at any
                    size); zoo-sweeps-K it checked by K sweeps at any size for K in FLAT_SWEEPS;
                    zoo-held it with labels held along the stream for the steps its classifier would
                    not fit in time (face held_labels), zoo-work-W-held both (zoo-work-40000-held
                    is the zoo route shipped since);
                    default-... the shipped default falling back to each
                    (docs/research/2026-12-07-large-steps-at-the-deadline.md)
    zoo-held-builtin  the zoo route as shipped (models/zoo.json's face), a step it would not label
                    in time solved on the labels held for its points and, for a point with none
                    held, Box2D's start read as labels (face held_from_builtin); default-held-builtin
                    the shipped default falling back to it
                    (docs/research/2026-12-07-new-points-of-a-held-step.md)
    zoo-repairK     the zoo route as shipped (models/zoo.json's face) with its answer repaired up to K
                    times (face repairs, for K in REPAIRS; three shipped since 2026-12-08, zoo-repair0
                    the route before), each island served whichever of Box2D's start, the answer and
                    its repairs stops it soonest; default-repairK the shipped default falling back
                    to it (docs/research/2026-12-08-repaired-labels.md)
    zoo-repair3-roundsR  the zoo route with three repairs, each admitted in R rounds (face
                    repair_rounds, for R in REPAIR_ROUNDS) where the route's answer has its 100;
                    default-repair3-roundsR the shipped default falling back to it
                    (docs/research/2026-12-08-cheaper-repairs.md)
    zoo-mirror      the zoo route as shipped on its classifier served with its mirror image (card
                    mirror: the mean of its answer and the reflected step's, reflected back);
                    default-zoo-mirror the shipped default falling back to it
                    (docs/research/2026-12-07-new-points-of-a-held-step.md)

Every variant here holds each point's bounce where the zoo's worlds have restitution (face
`restitution`, true unless a card says otherwise) since the evening of 2026-12-07; the figures the
notes before then give for these variants on the zoo's classes were measured with every point held
at rest (default-bounceless is the shipped default so; on worlds without restitution nothing
changed). Written to a temporary folder and renamed; an existing folder is replaced.
"""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

from lab.variants import ROOT, card, write_folder
from lab.variants import main as variants_main

STORE = ROOT / "lab" / "models"
FIRST = "graph-labels-scaled-zoo-first-r12-e4"
WIDER = "graph-labels-scaled-zoo500-r12-e4"
#: The shipped zoo classifier trained on (six more epochs on another draw of each file's steps), and
#: that network six epochs more on a third draw: (store name, its tag in the variants' names).
TRAINED_ON = (("graph-labels-scaled-zoo-r12-e4-s7-e6", "s7e6"), ("graph-labels-scaled-zoo-r12-e4-s7-e6-s9-e6", "s7e6-s9e6"))
#: The zoo route's face as shipped until its check counted the sweeps to the client's stopping rule
#: (2026-12-06): every zoo variant here changes this one, so that each keeps its meaning whatever
#: ships later; `zoo-before` serves it as it is.
ZOO_FACE = {"pressing": 0.75, "rounds": 50, "rho": 1000, "max_residual": 0.5, "max_points": 1000, "solver": "dual",
            "against_builtin": True, "check_sweeps": 12, "extrapolate_jointed": True, "fallback": "contact-graph"}
#: Sweeps of the zoo route's check against Box2D's start (face check_sweeps; 12 in ZOO_FACE).
CHECK_SWEEPS = (4, 24, 48, 96, 200)
#: Point-sweeps a start of the zoo route's check may play on a step, in zoo-work-W (face check_work).
CHECK_WORK = (10_000, 20_000, 40_000)
#: The zoo route's face as shipped until its check's work was capped and its labels held
#: (2026-12-07): zoo-work-..., zoo-sweeps-... and zoo-held change this one.
LARGE_BEFORE = {"pressing": 0.75, "rounds": 100, "rho": 1000, "max_residual": None, "max_points": 1000,
                "solver": "dual", "against_builtin": True, "check_sweeps": 200, "check_stop": True,
                "extrapolate_jointed": True, "min_rounds": 30, "revolute_joints": True, "by_island": True,
                "fallback": "contact-graph"}
#: Sweeps of the zoo route's check at any step size, in zoo-sweeps-K.
FLAT_SWEEPS = (50, 100)
#: Repairs of the zoo route's answer in zoo-repairK (face repairs).
REPAIRS = (0, 1, 2, 3, 5, 8)
#: Admission rounds of each of three repairs in zoo-repair3-roundsR (face repair_rounds).
REPAIR_ROUNDS = (10, 30, 100)
#: Repairs of the default's own route's answer in default-own-repairK (checked island by island).
OWN_REPAIRS = (0, 3)
#: Sweeps to the stopping rule of the default's own route's check in default-own-stopK.
OWN_STOP_SWEEPS = (48, 200)
#: max_residual x 10 of the zoo route in 200 rounds checked by 200 sweeps (0.5 shipped, at 50 rounds and 12 sweeps).
GATES = (5, 10, 20, 50)
#: Sweeps of the zoo route's check, without its gate and in 200 rounds, counted to the stopping rule.
STOP_SWEEPS = (48, 96, 200)
#: Admission rounds of the zoo route without its gate, checked by the sweeps to the stopping rule up to 200.
STOP_ROUNDS = (50, 100)
#: max_residual x 10 of those: a gate however loose sends the steps whose labels the compiled dual
#: declines to the fallback, where without one the route solves them piece by piece in Python.
STOP_GATES = (10, 50)


def _fill(tmp: Path) -> None:
    # The default's variants fall back to the zoo route as it was (zoo-before) unless they name another.
    face = {**json.loads((tmp / "default.json").read_text())["face"], "fallback": "zoo-before"}
    zoo_face = dict(ZOO_FACE)
    for store_name, name in ((FIRST, "zoo-first-modes"), (WIDER, "zoo500-modes"),
                             *((store, f"{tag}-modes") for store, tag in TRAINED_ON)):
        network = json.loads((STORE / f"{store_name}.json").read_text())
        network.update(name=name, onnx_file=f"{name}.onnx", measured=None)
        shutil.copy(STORE / f"{store_name}.onnx", tmp / f"{name}.onnx")
        (tmp / f"{name}.json").write_text(json.dumps(network, indent=1) + "\n")
    no_fallback = {k: v for k, v in face.items() if k != "fallback"}
    card(tmp, "default-bf", alias_of="contact-modes", face=no_fallback)
    card(tmp, "default-graph", alias_of="contact-modes", face={**face, "fallback": "contact-graph"})
    card(tmp, "zoo-first", alias_of="zoo-first-modes", face=zoo_face)
    # The network trained on, behind the zoo route and the default exactly as shipped.
    shipped_zoo, shipped_default = (json.loads((tmp / f"{n}.json").read_text()) for n in ("zoo", "default"))
    for _, tag in TRAINED_ON:
        card(tmp, f"zoo-{tag}", alias_of=f"{tag}-modes", face=shipped_zoo["face"])
        card(tmp, f"default-{tag}", alias_of=shipped_default["alias_of"],
             face={**shipped_default["face"], "fallback": f"zoo-{tag}"}, measured=shipped_default.get("measured"))
    for tag, by_island in (("island", True), ("whole", False)):
        card(tmp, f"zoo-{tag}", alias_of=shipped_zoo["alias_of"],
             face={**shipped_zoo["face"], "by_island": by_island, **({} if by_island else {"repairs": 0})})
        card(tmp, f"default-{tag}", alias_of=shipped_default["alias_of"],
             face={**shipped_default["face"], "fallback": f"zoo-{tag}"}, measured=shipped_default.get("measured"))
    for tag, bounce in (("bounce", True), ("bounceless", False)):
        card(tmp, f"zoo-{tag}", alias_of=shipped_zoo["alias_of"], face={**shipped_zoo["face"], "restitution": bounce})
        card(tmp, f"default-{tag}", alias_of=shipped_default["alias_of"],
             face={**shipped_default["face"], "fallback": f"zoo-{tag}", "restitution": bounce},
             measured=shipped_default.get("measured"))
    # The check's cost on large steps: capped by its work, by a flat count, and labels held; each a
    # change of the zoo route as it was before any of them (LARGE_BEFORE).
    large = {f"work-{w}": {"check_work": w} for w in CHECK_WORK}
    large.update({"work-none": {}, "held": {"held_labels": True}})
    large.update({f"sweeps-{k}": {"check_sweeps": k} for k in FLAT_SWEEPS})
    large.update({f"work-{w}-held": {"check_work": w, "held_labels": True} for w in CHECK_WORK})
    for tag, change in large.items():
        card(tmp, f"zoo-{tag}", alias_of=shipped_zoo["alias_of"], face={**LARGE_BEFORE, **change})
        card(tmp, f"default-{tag}", alias_of=shipped_default["alias_of"],
             face={**shipped_default["face"], "fallback": f"zoo-{tag}"}, measured=shipped_default.get("measured"))
    # The shipped zoo route with a held step's new points read from Box2D's start.
    card(tmp, "zoo-held-builtin", alias_of=shipped_zoo["alias_of"],
         face={**shipped_zoo["face"], "held_from_builtin": True})
    card(tmp, "default-held-builtin", alias_of=shipped_default["alias_of"],
         face={**shipped_default["face"], "fallback": "zoo-held-builtin"}, measured=shipped_default.get("measured"))
    # The shipped zoo route on its classifier and that classifier's mirror image, their mean.
    card(tmp, "zoo-mirror", alias_of=shipped_zoo["alias_of"], face=shipped_zoo["face"], mirror=True)
    card(tmp, "default-zoo-mirror", alias_of=shipped_default["alias_of"],
         face={**shipped_default["face"], "fallback": "zoo-mirror"}, measured=shipped_default.get("measured"))
    # The shipped zoo route with its answer repaired up to K times, each island served the soonest.
    for k in REPAIRS:
        repaired = {**shipped_zoo["face"], "repairs": k}
        if not k:
            repaired.pop("repair_rounds", None)  # only with repairs
        card(tmp, f"zoo-repair{k}", alias_of=shipped_zoo["alias_of"], face=repaired)
        card(tmp, f"default-repair{k}", alias_of=shipped_default["alias_of"],
             face={**shipped_default["face"], "fallback": f"zoo-repair{k}"}, measured=shipped_default.get("measured"))
    # Three repairs, each admitted in R rounds rather than the route's.
    for r in REPAIR_ROUNDS:
        card(tmp, f"zoo-repair3-rounds{r}", alias_of=shipped_zoo["alias_of"],
             face={**shipped_zoo["face"], "repairs": 3, "repair_rounds": r})
        card(tmp, f"default-repair3-rounds{r}", alias_of=shipped_default["alias_of"],
             face={**shipped_default["face"], "fallback": f"zoo-repair3-rounds{r}"},
             measured=shipped_default.get("measured"))
    # The default's own route checked island by island to the stopping rule, up to 200 sweeps, and
    # its answer repaired up to K times (repairs need the check by islands).
    for k in OWN_REPAIRS:
        card(tmp, f"default-own-repair{k}", alias_of=shipped_default["alias_of"],
             face={**shipped_default["face"], "check_stop": True, "check_sweeps": 200, "by_island": True, "repairs": k},
             measured=shipped_default.get("measured"))
    for sweeps in OWN_STOP_SWEEPS:
        card(tmp, f"default-own-stop{sweeps}", alias_of=shipped_default["alias_of"],
             face={**shipped_default["face"], "check_stop": True, "check_sweeps": sweeps},
             measured=shipped_default.get("measured"))
    card(tmp, "zoo-bf", alias_of="contact-modes-zoo", face={k: v for k, v in zoo_face.items() if k != "fallback"})
    card(tmp, "zoo-always", alias_of="contact-modes-zoo",
         face={**{k: v for k, v in zoo_face.items() if k != "fallback"}, "max_points": 5000, "max_residual": None})
    card(tmp, "zoo-r0.6", alias_of="contact-modes-zoo", face={**zoo_face, "max_residual": 0.6})
    card(tmp, "default-r0.6", alias_of="contact-modes", face={**face, "max_residual": 0.6})
    card(tmp, "default-first", alias_of="contact-modes", face={**face, "fallback": "zoo-first"})
    card(tmp, "zoo500", alias_of="zoo500-modes", face=zoo_face)
    card(tmp, "default-zoo500", alias_of="contact-modes", face={**face, "fallback": "zoo500"})
    card(tmp, "zoo-unchecked", alias_of="contact-modes-zoo", face={**zoo_face, "against_builtin": False})
    card(tmp, "default-unchecked", alias_of="contact-modes", face={**face, "fallback": "zoo-unchecked"})
    card(tmp, "zoo-r200", alias_of="contact-modes-zoo", face={**zoo_face, "rounds": 200})
    ungated = {**zoo_face, "max_residual": None}
    card(tmp, "zoo-ungated", alias_of="contact-modes-zoo", face=ungated)
    card(tmp, "zoo-ungated-r200", alias_of="contact-modes-zoo", face={**ungated, "rounds": 200})
    card(tmp, "zoo-ungated-r200-unchecked", alias_of="contact-modes-zoo",
         face={**ungated, "rounds": 200, "against_builtin": False, "check_sweeps": None})
    for sweeps in CHECK_SWEEPS:
        for name, base in ((f"zoo-check{sweeps}", zoo_face), (f"zoo-ungated-r200-check{sweeps}", {**ungated, "rounds": 200})):
            card(tmp, name, alias_of="contact-modes-zoo", face={**base, "check_sweeps": sweeps})
            card(tmp, f"default-{name}", alias_of="contact-modes", face={**face, "fallback": name})
    card(tmp, "zoo-before", alias_of="contact-modes-zoo", face=zoo_face)
    card(tmp, "default-zoo-before", alias_of="contact-modes", face={**face, "fallback": "zoo-before"})
    stop = {"check_stop": True}
    card(tmp, "zoo-stop", alias_of="contact-modes-zoo", face={**zoo_face, **stop})
    card(tmp, "default-zoo-stop", alias_of="contact-modes", face={**face, "fallback": "zoo-stop"})
    card(tmp, "default-stop", alias_of="contact-modes", face={**face, **stop})
    for sweeps in STOP_SWEEPS:
        name = f"zoo-ungated-r200-check{sweeps}-stop"
        card(tmp, name, alias_of="contact-modes-zoo", face={**ungated, "rounds": 200, "check_sweeps": sweeps, **stop})
        card(tmp, f"default-{name}", alias_of="contact-modes", face={**face, "fallback": name})
        card(tmp, f"default-stop-{name}", alias_of="contact-modes", face={**face, **stop, "fallback": name})
    for rounds in STOP_ROUNDS:
        name = f"zoo-ungated-r{rounds}-check200-stop"
        card(tmp, name, alias_of="contact-modes-zoo", face={**ungated, "rounds": rounds, "check_sweeps": 200, **stop})
        card(tmp, f"default-{name}", alias_of="contact-modes", face={**face, "fallback": name})
        for gate in STOP_GATES:
            name = f"zoo-res{gate}-r{rounds}-check200-stop"
            card(tmp, name, alias_of="contact-modes-zoo",
                 face={**zoo_face, "max_residual": gate / 10, "rounds": rounds, "check_sweeps": 200, **stop})
            card(tmp, f"default-{name}", alias_of="contact-modes", face={**face, "fallback": name})
    for gate in GATES:
        name = f"zoo-res{gate}-r200-check200"
        card(tmp, name, alias_of="contact-modes-zoo",
             face={**zoo_face, "max_residual": gate / 10, "rounds": 200, "check_sweeps": 200})
        card(tmp, f"default-{name}", alias_of="contact-modes", face={**face, "fallback": name})


def build(out: Path) -> None:
    """Write the folder the module docstring describes at `out`."""
    write_folder(out, _fill)


def main(argv: list[str] | None = None) -> int:
    return variants_main(argv, "python -m lab.zoo_variants", __doc__, build)


if __name__ == "__main__":
    sys.exit(main())
