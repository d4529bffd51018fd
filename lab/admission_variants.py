"""A model folder with the default's route variants (its admission, its classifier's mirror image,
its classifier trained on reflected steps)
beside the shipped models, for pricing them on the same states
(docs/research/2026-12-06-over-relaxed-admission.md):

    python -m lab.admission_variants runs/admission-variants
    deepcontact lab iterations --seeds 850-899 --deadline-ms 1000 --models runs/admission-variants \
        --warm-starts builtin,price:server:default-r50-x10+server:default-r50-x15+server:default-r40-x16+...

Beside models/ it writes alias cards over the shipped classifiers, each with the shipped card's
`face` but the admission's rounds and over-relaxation changed:

    default-rR-xX   the default's route, R rounds over-relaxed by X / 10 (x10: plain ADMM, as the
                    default's route was until its 40 rounds at 1.6); for (R, X) in VARIANTS
    zoo-r40-x16     the zoo route with the default's setting (the zoo keeps 50 plain rounds)
    default-mirror  the default's route as shipped on its classifier served with its mirror image
                    (modes-mirror: graph-face-fr-r12-e15-mirror of the research store, with
                    contact-modes' trained_on and measured), as until 2026-12-06
    default-mirrored the same answers (to float32 rounding) from the shipped classifier with the
                    card's `mirror`: the reflected half as a second call on the spare core
                    (server.mirror_image), where default-mirror runs both in one
    default-aug     the default's route as shipped on its classifier trained two more epochs with
                    half the steps reflected (modes-aug: graph-face-fr-r12-e15-aug of the
                    research store, with contact-modes' trained_on and measured)
    default-against-builtin  the default's route as shipped, its answer checked against Box2D's
                    start by one projected Jacobi step as the zoo route's is (face
                    `against_builtin`; docs/research/2026-12-06-the-route-against-box2ds-start.md)
    default-graph-mirror  the default whose last fallback is contact-graph served with its mirror
                    image in one ONNX graph (graph-mirror: graph-projected-max-1-799-r8-e9-reflect-sym-mirror
                    of the research store, with contact-graph's trained_on), through zoo-graph-mirror,
                    as until 2026-12-06 (docs/research/2026-12-06-the-graph-fallbacks-share.md)
    default-no-graph  the default with no graph fallback: where both routes miss, Box2D's start
                    (through zoo-no-graph, the zoo route without a fallback)
    default-resR    the default's route with max_residual R / 100 (resnone: none, every reading
                    served), for R in RESIDUALS: how far the admitted solve may miss its labels
                    before the fallback answers (docs/research/2026-12-06-the-graph-fallbacks-share.md)
    zoo-resR, default-zoo-resR  the zoo route with max_residual R / 100, and the default falling
                    back to it, for R in ZOO_RESIDUALS (the default serves the zoo route on worlds
                    contact-modes was not trained on)
    zoo-rhoR, default-rhoR  the zoo route, and the default with both its routes, admitting at
                    ADMM's penalty (face `rho`) R, for R in RHOS (default-rho100: the default as
                    it was until 2026-12-06; default-rho1000: as shipped); default-rhoR-rN the
                    same with its own route in N rounds, for R 100 and 1000 and N in RHO_ROUNDS;
                    default-rho1000-xX its own route over-relaxed by X / 10 (RHO_RELAX);
                    zoo-rho1000-x13, -x16 (50 rounds over-relaxed), -r40-x16 (40 of them), and the
                    default falling back to each, default-zoo-rho1000-...
                    (docs/research/2026-12-06-the-admissions-penalty.md)
    zoo-carry, default-carry  the zoo route, and the default with both its routes, whose
                    admission goes on along the stream from where each point's stopped on the
                    step before (face `carry`, deepcontact.admission.AdmissionCarry);
                    default-carry-rN the same with its own route in N rounds (CARRY_ROUNDS),
                    default-carry-own only its own route carried, default-carry-against-builtin
                    both carried and its own answer checked against Box2D's start
    default-uncarried, zoo-jacobi  the default and the zoo route as shipped until the last change of
                    2026-12-06: the default's own route neither carried nor checked, the zoo's
                    checked by one Jacobi step
    default-checkK  the default's own route checked against Box2D's start by the solver's K-th
                    sweep from each (face `against_builtin` with `check_sweeps` K,
                    deepcontact.faces.sweep_changes), for K in CHECK_SWEEPS; zoo-checkK and
                    default-zoo-checkK the zoo route's check so (one Jacobi step as shipped);
                    default-all-checkK both checked so; default-carry-checkK with both routes
                    carried, default-own-carry-checkK only its own (the zoo route as shipped),
                    default-own-carry-all-checkK only its own, both checked;
                    default-carry-r50-checkK, -all- both carried, its own in 50 rounds
    default-shipped-rN  the default as shipped (carried, checked, extrapolated at jointed points) with
                    its own route's admission in N rounds (SHIPPED_ROUNDS; 40 shipped): what the
                    carried start lets the server stop earlier
    zoo-before      the zoo route as lab.zoo_variants.ZOO_FACE has it, which every zoo variant here changes
    default-jointed-builtin  the default as shipped but at its points on jointed bodies Box2D's
                    start as it is, not extrapolated in time along the stream (face
                    `extrapolate_jointed`, deepcontact.temporal; every variant above is without it)

Written to a temporary folder and renamed; an existing folder is replaced.
"""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

from lab.variants import ROOT, card, write_folder
from lab.variants import main as variants_main
from lab.zoo_variants import ZOO_FACE

#: (rounds, relax x 10) of the default's route variants.
VARIANTS = ((50, 10), (50, 15), (40, 16), (30, 15), (30, 17), (25, 18), (20, 18))
#: The default's classifier with its mirror image, and trained on reflected steps, in the research store.
MIRROR, AUGMENTED = "graph-face-fr-r12-e15-mirror", "graph-face-fr-r12-e15-aug"
#: The graph fallback as it was served until 2026-12-06: the network and its mirror image in one graph.
GRAPH_MIRROR = "graph-projected-max-1-799-r8-e9-reflect-sym-mirror"
#: max_residual of the default's route variants (a share of the step's velocities; None: none).
RESIDUALS = (0.3, 0.35, 0.4, 0.5, 0.75, 1.0, None)
#: max_residual of the zoo route's variants.
ZOO_RESIDUALS = (0.3, 0.5, 0.75)
#: The admission's ADMM penalty (face `rho`) of the routes' variants.
RHOS = (30, 100, 300, 1000, 3000)
#: Rounds of the default's route at the penalties 100 and 1000 (for what more rounds would buy).
RHO_ROUNDS = (60, 80, 120, 200, 1000)
#: Over-relaxations (x 10) of the default's route at the penalty 1000 (tuned at 100: 1.6).
RHO_RELAX = (14, 18, 19)
#: Rounds of the default's route with its admission carried along the stream.
CARRY_ROUNDS = (10, 20, 30, 50, 60)
#: Rounds of the default's own route as shipped (carried, checked), for fewer than its 40.
SHIPPED_ROUNDS = (20, 25, 30, 35)
#: Sweeps of the check against Box2D's start (face check_sweeps).
CHECK_SWEEPS = (4, 8, 12, 16, 24)


def _fill(tmp: Path) -> None:
    default = json.loads((tmp / "default.json").read_text())
    # The zoo route as it was until its check counted sweeps to the stopping rule (lab.zoo_variants).
    zoo = {**json.loads((tmp / "zoo.json").read_text()), "face": dict(ZOO_FACE)}
    card(tmp, "zoo-before", alias_of=zoo["alias_of"], face=zoo["face"])
    # Every variant below changes the routes as they were until 2026-12-06's last change (the
    # default's own route neither carried nor checked, the zoo's checked by one Jacobi step), so
    # that each keeps its meaning whatever ships later; those of carry and check_sweeps add them.
    plain = {"carry": False, "against_builtin": False, "check_sweeps": None, "extrapolate_jointed": False,
             "check_stop": False}
    # The default as shipped but for Box2D's start extrapolated at its jointed points (face
    # extrapolate_jointed, shipped on 2026-12-06 after everything above): Box2D's start as it is there.
    card(tmp, "default-jointed-builtin", alias_of=default["alias_of"],
         face={**default["face"], "extrapolate_jointed": False})
    for rounds in SHIPPED_ROUNDS:
        card(tmp, f"default-shipped-r{rounds}", alias_of=default["alias_of"], face={**default["face"], "rounds": rounds})
    card(tmp, "zoo-jacobi", alias_of=zoo["alias_of"], face={**zoo["face"], "check_sweeps": None,
                                                           "extrapolate_jointed": False})
    default = {**default, "face": {**default["face"], **plain, "fallback": "zoo-jacobi"}}
    zoo = {**zoo, "face": {**zoo["face"], "check_sweeps": None, "extrapolate_jointed": False}}
    for rounds, relax in VARIANTS:
        card(tmp, f"default-r{rounds}-x{relax}", alias_of=default["alias_of"],
             face={**default["face"], "rounds": rounds, "relax": relax / 10})
    card(tmp, "zoo-r40-x16", alias_of=zoo["alias_of"], face={**zoo["face"], "rounds": 40, "relax": 1.6})
    modes = json.loads((tmp / "contact-modes.json").read_text())
    graph = json.loads((tmp / "contact-graph.json").read_text())
    for store_name, name, like in ((MIRROR, "modes-mirror", modes), (AUGMENTED, "modes-aug", modes),
                                   (GRAPH_MIRROR, "graph-mirror", graph)):
        network = json.loads((ROOT / "lab" / "models" / f"{store_name}.json").read_text())
        network.update(name=name, onnx_file=f"{name}.onnx", trained_on=like.get("trained_on"),
                       measured=like.get("measured"))
        shutil.copy(ROOT / "lab" / "models" / f"{store_name}.onnx", tmp / f"{name}.onnx")
        (tmp / f"{name}.json").write_text(json.dumps(network, indent=1) + "\n")
    card(tmp, "default-mirror", alias_of="modes-mirror", face=default["face"], measured=default.get("measured"))
    card(tmp, "default-aug", alias_of="modes-aug", face=default["face"], measured=default.get("measured"))
    card(tmp, "default-mirrored", alias_of=default["alias_of"], face=default["face"], mirror=True,
         measured=default.get("measured"))
    card(tmp, "default-against-builtin", alias_of=default["alias_of"], face={**default["face"], "against_builtin": True})
    card(tmp, "zoo-graph-mirror", alias_of=zoo["alias_of"], face={**zoo["face"], "fallback": "graph-mirror"})
    card(tmp, "default-graph-mirror", alias_of=default["alias_of"], face={**default["face"], "fallback": "zoo-graph-mirror"})
    card(tmp, "zoo-no-graph", alias_of=zoo["alias_of"], face={k: v for k, v in zoo["face"].items() if k != "fallback"})
    card(tmp, "default-no-graph", alias_of=default["alias_of"], face={**default["face"], "fallback": "zoo-no-graph"})
    for residual in RESIDUALS:
        card(tmp, residual_variant(residual), alias_of=default["alias_of"],
             face={**default["face"], "max_residual": residual})
    for residual in ZOO_RESIDUALS:
        zoo_variant = residual_variant(residual).replace("default", "zoo")
        card(tmp, zoo_variant, alias_of=zoo["alias_of"], face={**zoo["face"], "max_residual": residual})
        card(tmp, f"default-{zoo_variant}", alias_of=default["alias_of"], face={**default["face"], "fallback": zoo_variant})
    for rho in RHOS:
        card(tmp, f"zoo-rho{rho}", alias_of=zoo["alias_of"], face={**zoo["face"], "rho": float(rho)})
        card(tmp, f"default-rho{rho}", alias_of=default["alias_of"],
             face={**default["face"], "rho": float(rho), "fallback": f"zoo-rho{rho}"})
    for rho in (100, 1000):
        for rounds in RHO_ROUNDS:
            card(tmp, f"default-rho{rho}-r{rounds}", alias_of=default["alias_of"],
                 face={**default["face"], "rho": float(rho), "rounds": rounds, "fallback": f"zoo-rho{rho}"})
    for relax in RHO_RELAX:
        card(tmp, f"default-rho1000-x{relax}", alias_of=default["alias_of"],
             face={**default["face"], "rho": 1000.0, "relax": relax / 10, "fallback": "zoo-rho1000"})
    for name, change in (("zoo-rho1000-x13", {"relax": 1.3}), ("zoo-rho1000-x16", {"relax": 1.6}),
                         ("zoo-rho1000-r40-x16", {"relax": 1.6, "rounds": 40})):
        card(tmp, name, alias_of=zoo["alias_of"], face={**zoo["face"], "rho": 1000.0, **change})
        card(tmp, f"default-{name}", alias_of=default["alias_of"], face={**default["face"], "fallback": name})
    card(tmp, "zoo-carry", alias_of=zoo["alias_of"], face={**zoo["face"], "carry": True})
    card(tmp, "default-carry", alias_of=default["alias_of"], face={**default["face"], "carry": True, "fallback": "zoo-carry"})
    card(tmp, "default-carry-own", alias_of=default["alias_of"], face={**default["face"], "carry": True})
    card(tmp, "default-carry-against-builtin", alias_of=default["alias_of"],
         face={**default["face"], "carry": True, "against_builtin": True, "fallback": "zoo-carry"})
    for rounds in CARRY_ROUNDS:
        card(tmp, f"default-carry-r{rounds}", alias_of=default["alias_of"],
             face={**default["face"], "carry": True, "rounds": rounds, "fallback": "zoo-carry"})
    card(tmp, "default-uncarried", alias_of=default["alias_of"], face=default["face"])
    checked = {"against_builtin": True}
    for sweeps in CHECK_SWEEPS:
        check = {**checked, "check_sweeps": sweeps}
        card(tmp, f"zoo-check{sweeps}", alias_of=zoo["alias_of"], face={**zoo["face"], **check})
        card(tmp, f"zoo-carry-check{sweeps}", alias_of=zoo["alias_of"], face={**zoo["face"], **check, "carry": True})
        card(tmp, f"default-check{sweeps}", alias_of=default["alias_of"], face={**default["face"], **check})
        card(tmp, f"default-zoo-check{sweeps}", alias_of=default["alias_of"],
             face={**default["face"], "fallback": f"zoo-check{sweeps}"})
        card(tmp, f"default-all-check{sweeps}", alias_of=default["alias_of"],
             face={**default["face"], **check, "fallback": f"zoo-check{sweeps}"})
        card(tmp, f"default-carry-check{sweeps}", alias_of=default["alias_of"],
             face={**default["face"], **check, "carry": True, "fallback": "zoo-carry"})
        card(tmp, f"default-own-carry-check{sweeps}", alias_of=default["alias_of"],
             face={**default["face"], **check, "carry": True})
        card(tmp, f"default-own-carry-all-check{sweeps}", alias_of=default["alias_of"],
             face={**default["face"], **check, "carry": True, "fallback": f"zoo-check{sweeps}"})
        card(tmp, f"default-carry-r50-check{sweeps}", alias_of=default["alias_of"],
             face={**default["face"], **check, "carry": True, "rounds": 50, "fallback": "zoo-carry"})
        card(tmp, f"default-carry-r50-all-check{sweeps}", alias_of=default["alias_of"],
             face={**default["face"], **check, "carry": True, "rounds": 50, "fallback": f"zoo-carry-check{sweeps}"})


def residual_variant(residual: float | None) -> str:
    """The name of the default's route variant with this max_residual: default-res50 for 0.5."""
    return "default-resnone" if residual is None else f"default-res{round(100 * residual)}"


def build(out: Path) -> None:
    """Write the folder the module docstring describes at `out`."""
    write_folder(out, _fill)


def main(argv: list[str] | None = None) -> int:
    return variants_main(argv, "python -m lab.admission_variants", __doc__, build)


if __name__ == "__main__":
    sys.exit(main())
