"""training.new_points_card: a second card for the same ONNX, applied to new points only."""

from deepcontact.modelcard import ModelCard
from tests.server.conftest import write_conv_model
from training.new_points_card import main


def test_the_new_points_card_serves_the_same_model_only_where_points_are_new(tmp_path):
    card = write_conv_model(tmp_path, "residual", combine="residual")
    assert main([str(tmp_path / "residual.json")]) == 0
    twin = ModelCard.load(tmp_path / "residual-new-points.json")
    assert twin.name == "residual-new-points" and twin.combine == "new-points"
    assert twin.onnx_file == card.onnx_file and twin.gridspec == card.gridspec


def test_a_missing_card_is_one_line_and_status_2(tmp_path, capsys):
    assert main([str(tmp_path / "nope.json")]) == 2
    assert "no model card" in capsys.readouterr().err
