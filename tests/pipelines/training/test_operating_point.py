"""A detector's operating point: after the shift, the product's threshold keeps exactly the cells the chosen score
kept before, and the ranking of the scores is unchanged."""

import pytest
import torch

from models.checkpoint import Checkpoint, load_checkpoint, save_checkpoint
from models.registry import create_model
from pipelines.jobs import run_module
from pipelines.training.operating_point import write_operating_point
from radar.centres import SCORE_THRESHOLD


def _detector(tmp_path):
    torch.manual_seed(0)
    model = create_model("centre_detector_tiny", preset="small").eval()
    return save_checkpoint(Checkpoint(model_name="centre_detector_tiny", config={"preset": "small"},
                                      state_dict=model.state_dict(), preset="small",
                                      class_names=("background", "pedestrian", "cyclist", "car"),
                                      extra={"stage": "detector"}), tmp_path / "det.pt")


def test_the_threshold_keeps_after_the_shift_what_the_score_kept_before(tmp_path):
    source = _detector(tmp_path)
    frame = torch.randn(2, 32, 128, 128)
    with torch.no_grad():
        before = load_checkpoint(source).build().eval()(frame)["heatmap"]
    score = float(before.flatten().quantile(0.95))  # a score some cells pass
    record = write_operating_point(source, tmp_path / "tuned.pt", score)
    with torch.no_grad():
        after = load_checkpoint(tmp_path / "tuned.pt").build().eval()(frame)["heatmap"]
    kept_before, kept_after = before >= score, after >= SCORE_THRESHOLD
    assert 0 < kept_before.sum() < kept_before.numel()
    assert (kept_before != kept_after).sum() <= 2  # float rounding at the boundary only
    assert torch.equal(before.flatten().argsort()[-50:].sort().values, after.flatten().argsort()[-50:].sort().values)
    assert load_checkpoint(tmp_path / "tuned.pt").extra["operating_point"] == record


@pytest.mark.parametrize("score", ["0", "1", "-0.2"])
def test_a_score_outside_zero_to_one_is_refused(tmp_path, score, capsys):
    assert run_module("pipelines.training.operating_point",
                      [str(_detector(tmp_path)), str(tmp_path / "t.pt"), "--score", score]) == 2
    assert "--score must be a heatmap score in (0, 1)" in capsys.readouterr().err
    assert not (tmp_path / "t.pt").exists()
