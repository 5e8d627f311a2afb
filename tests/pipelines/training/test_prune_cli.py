"""`radarseg prune` stores float16 when asked (--half) or when its input was float16: smaller on disk."""

from __future__ import annotations

import torch

from models.checkpoint import Checkpoint, load_checkpoint, save_checkpoint, stored_as
from models.registry import create_model
from pipelines.cli import main
from radar.profiles import get_profile


def _saved(tmp_path, *, float16: bool):
    torch.manual_seed(0)
    model = create_model("minkunet_tiny", preset="small")
    checkpoint = Checkpoint(model_name="minkunet_tiny", config={"preset": "small"}, state_dict=model.state_dict(),
                            preset="small", class_names=tuple(get_profile("small").all_class_names))
    return save_checkpoint(stored_as(checkpoint, float16=float16), tmp_path / f"in{int(float16)}.pt")


def _dtypes(path) -> set[torch.dtype]:
    return {v.dtype for v in load_checkpoint(path).state_dict.values() if v.is_floating_point()}


def test_prune_keeps_float16_inputs_float16_and_half_halves_float32_ones(tmp_path, capsys):
    shipped = _saved(tmp_path, float16=True)
    assert main(["prune", "--checkpoint", str(shipped), "--ratio", "0.3", "--out", str(tmp_path / "a.pt")]) == 0
    assert "stored float16" in capsys.readouterr().out
    assert _dtypes(tmp_path / "a.pt") == {torch.float16}
    assert load_checkpoint(tmp_path / "a.pt").extra["stored_dtype"] == "float16"

    trained = _saved(tmp_path, float16=False)
    assert main(["prune", "--checkpoint", str(trained), "--ratio", "0.3", "--out", str(tmp_path / "b.pt")]) == 0
    assert _dtypes(tmp_path / "b.pt") == {torch.float32}
    assert main(["prune", "--checkpoint", str(trained), "--ratio", "0.3", "--half", "--out",
                 str(tmp_path / "c.pt")]) == 0
    assert _dtypes(tmp_path / "c.pt") == {torch.float16}
    assert (tmp_path / "c.pt").stat().st_size < 0.7 * (tmp_path / "b.pt").stat().st_size
    load_checkpoint(tmp_path / "c.pt").build()  # float16 weights load into the float32 model
    assert main(["prune", "--checkpoint", str(shipped), "--ratio", "0.3", "--no-half", "--out",
                 str(tmp_path / "d.pt")]) == 0
    assert _dtypes(tmp_path / "d.pt") == {torch.float32}
