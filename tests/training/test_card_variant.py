"""training.card_variant: the same ONNX served another way."""

from deepcontact.modelcard import ModelCard
from tests.server.conftest import write_conv_model
from training.card_variant import main


def test_a_new_points_variant_serves_the_same_model_only_where_points_are_new(tmp_path):
    card = write_conv_model(tmp_path, "residual", combine="residual")
    assert main([str(tmp_path / "residual.json"), "--combine", "new-points"]) == 0
    twin = ModelCard.load(tmp_path / "residual-new-points.json")
    assert twin.name == "residual-new-points" and twin.combine == "new-points"
    assert twin.onnx_file == card.onnx_file and twin.gridspec == card.gridspec


def test_a_scaled_variant_keeps_its_combine_and_shrinks_the_correction(tmp_path):
    write_conv_model(tmp_path, "residual", combine="residual")
    assert main([str(tmp_path / "residual.json"), "--correction-scale", "0.5"]) == 0
    half = ModelCard.load(tmp_path / "residual-x0.5.json")
    assert half.combine == "residual" and half.correction_scale == 0.5


def test_a_thresholded_variant_drops_small_corrections(tmp_path):
    write_conv_model(tmp_path, "residual", combine="residual")
    assert main([str(tmp_path / "residual.json"), "--correction-threshold", "0.2"]) == 0
    sparse = ModelCard.load(tmp_path / "residual-t0.2.json")
    assert sparse.combine == "residual" and sparse.correction_threshold == 0.2 and sparse.correction_scale == 1.0


def test_bad_requests_are_one_line_and_status_2(tmp_path, capsys):
    assert main([str(tmp_path / "nope.json"), "--combine", "new-points"]) == 2
    assert "no model card" in capsys.readouterr().err
    write_conv_model(tmp_path, "residual", combine="residual")
    assert main([str(tmp_path / "residual.json")]) == 2
    assert "nothing to change" in capsys.readouterr().err


def test_only_a_graph_residual_model_runs_a_second_pass_from_its_first(tmp_path, capsys):
    write_conv_model(tmp_path, "residual", combine="residual")
    assert main([str(tmp_path / "residual.json"), "--passes", "2"]) == 2
    assert "passes 2: only a graph model" in capsys.readouterr().err
    assert not (tmp_path / "residual-p2.json").exists()
