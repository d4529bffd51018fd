"""lab.admission_variants: the shipped models with the admission's variants beside them, all servable."""

from __future__ import annotations

from lab.admission_variants import RESIDUALS, RHOS, VARIANTS, ZOO_RESIDUALS, main, residual_variant
from server.predictors import load_models


def test_the_variants_folder_serves_the_shipped_models_and_each_admission_setting(tmp_path):
    out = tmp_path / "variants"
    out.mkdir()
    (out / "stale.json").write_text("{}")  # a folder already there is replaced
    assert main([str(out)]) == 0
    served = {p.name: p for p in load_models(out)}
    names = {f"default-r{rounds}-x{relax}" for rounds, relax in VARIANTS}
    assert names | {"default", "zoo", "zoo-r40-x16"} <= set(served)
    assert not (out / "stale.json").exists() and not out.with_name("variants.part").exists()
    # Each variant changes the routes as they were before the admission was carried and checked by
    # sweeps (default-uncarried, falling back to zoo-jacobi): the shipped routes with those off.
    base = served["default-uncarried"].settings
    # Its zoo variants change the zoo route as it was before its check counted sweeps to the stopping rule.
    shipped, zoo = served["default"].settings, served["zoo-before"].settings
    assert shipped["carry"] and shipped["check_sweeps"] == 12 and zoo["check_sweeps"] == 12 and not zoo["carry"]
    off = {"carry": False, "against_builtin": False, "check_sweeps": None, "extrapolate_jointed": False, "check_stop": False,
           "fallback": "zoo-jacobi"}
    assert base == {**shipped, **off}
    assert served["zoo-jacobi"].settings == {**zoo, "check_sweeps": None, "extrapolate_jointed": False}
    # ... and the shipped default is the variant that adds them back (its fallback renamed), then
    # draws Box2D's start on at its jointed points (default-jointed-builtin: all but that).
    chosen = served["default-own-carry-all-check12"]
    assert {**chosen.settings, "fallback": "zoo", "extrapolate_jointed": True} == shipped
    assert chosen.fallback.settings == {**zoo, "extrapolate_jointed": False}
    assert served["default-jointed-builtin"].settings == {**shipped, "extrapolate_jointed": False}
    assert served["default-jointed-builtin"].fallback.name == "zoo" and shipped["extrapolate_jointed"]
    assert served["default-carry-check12"].fallback.settings["carry"]  # both routes carried there
    # The default as shipped in fewer admission rounds: only its rounds change, its fallback the shipped zoo route.
    fewer = served["default-shipped-r30"]
    assert fewer.settings == {**shipped, "rounds": 30} and fewer.fallback.name == "zoo"
    # Each is the route with only its setting changed: the same classifier and fallback chain,
    # here its rounds and over-relaxation as named.
    plain = served["default-r50-x10"].settings
    assert (plain["rounds"], plain["relax"]) == (50, 1.0)
    assert {k: v for k, v in plain.items() if k not in ("rounds", "relax")} == \
        {k: v for k, v in base.items() if k not in ("rounds", "relax")}
    assert served["default-r50-x10"].fallback.name == "zoo-jacobi"
    assert (served["zoo-r40-x16"].settings["rounds"], served["zoo-r40-x16"].settings["relax"]) == (40, 1.6)
    # The mirrored classifier under the default's route, trusted where contact-modes is.
    assert served["default-mirror"].settings == base
    assert served["default-mirror"].envelope == served["default"].envelope
    assert served["default-mirror"].wins_where_trained
    # The same mirror image as two calls, the reflected one on the spare core.
    from server.mirror_image import MirroredGraphPredictor

    assert isinstance(served["default-mirrored"].classifier, MirroredGraphPredictor)
    assert served["default-mirrored"].settings == base
    # The classifier trained on reflected steps under the default's route.
    assert served["default-aug"].settings == base
    assert served["default-aug"].classifier.card.onnx_file == "modes-aug.onnx"
    # The default's route with its answer checked against Box2D's start, as the zoo route's is.
    checked = served["default-against-builtin"].settings
    assert checked["against_builtin"] and not base["against_builtin"] and checked["check_sweeps"] is None
    assert {k: v for k, v in checked.items() if k != "against_builtin"} == \
        {k: v for k, v in base.items() if k != "against_builtin"}
    # The graph fallback as it was served, with its mirror image in one graph, and no graph fallback
    # at all: the same routes, only the last fallback changed.
    from server.predictors import GraphPredictor

    mirrored = served["default-graph-mirror"].fallback
    assert mirrored.name == "zoo-graph-mirror"
    assert {k: v for k, v in mirrored.settings.items() if k != "fallback"} == \
        {k: v for k, v in served["zoo-jacobi"].settings.items() if k != "fallback"}
    assert isinstance(mirrored.fallback, GraphPredictor) and mirrored.fallback.name == "graph-mirror"
    assert mirrored.fallback.envelope == served["contact-graph"].envelope
    assert served["default-no-graph"].fallback.name == "zoo-no-graph"
    assert served["default-no-graph"].fallback.fallback is None
    assert served["default"].fallback.fallback.name == "contact-graph"
    # How far the admitted solve may miss its labels before the fallback answers, each else as shipped.
    for residual in RESIDUALS:
        settings = served[residual_variant(residual)].settings
        assert settings["max_residual"] == residual
        assert {k: v for k, v in settings.items() if k != "max_residual"} == \
            {k: v for k, v in base.items() if k != "max_residual"}
    assert residual_variant(0.35) == "default-res35" and residual_variant(None) == "default-resnone"
    # The zoo route's own test, and the default falling back to each.
    for residual in ZOO_RESIDUALS:
        zoo = served[f"default-zoo-res{round(100 * residual)}"].fallback
        assert zoo.name == f"zoo-res{round(100 * residual)}" and zoo.settings["max_residual"] == residual
        assert zoo.fallback.name == "contact-graph" and zoo.settings["against_builtin"]
    # The admission's ADMM penalty on both routes, each else as shipped.
    for rho in RHOS:
        own, zoo = served[f"default-rho{rho}"].settings, served[f"default-rho{rho}"].fallback
        assert own["rho"] == rho and zoo.name == f"zoo-rho{rho}" and zoo.settings["rho"] == rho
        assert {k: v for k, v in own.items() if k not in ("rho", "fallback")} == \
            {k: v for k, v in base.items() if k not in ("rho", "fallback")}
    assert served["default-rho100-r200"].settings["rounds"] == 200 and served["default-rho100-r200"].settings["rho"] == 100
    assert served["default-rho1000-x18"].settings["relax"] == 1.8 and served["default-rho1000-x18"].settings["rho"] == 1000
    relaxed = served["default-zoo-rho1000-r40-x16"].fallback.settings
    assert (relaxed["rounds"], relaxed["relax"], relaxed["rho"]) == (40, 1.6, 1000)
