"""Options that took a new name are refused under the old one with a line naming the new one (exit code 2)."""

from __future__ import annotations

import pytest

from pipelines.cli import main


@pytest.mark.parametrize("argv", [
    ["train", "detector", "--store", "s.zarr", "--out", "runs/d", "--profile", "quick"],
    ["train-baseline", "tmvanet", "--store", "s.zarr", "--out", "runs/t", "--profile", "paper"],
])
def test_training_refuses_profile_naming_recipe(argv, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert "--profile is now --recipe" in err and "Traceback" not in err


def test_recipe_reaches_the_training_config():
    from pipelines.jobs import job_module, parse_config

    cfg = parse_config(job_module("pipelines.training.train"), ["detector", "--store", "s.zarr", "--out", "o",
                                                                 "--recipe", "paper"], "radarseg train")
    assert cfg.recipe == "paper" and cfg.hyper().epochs == 300


def test_a_run_saved_with_profile_resumes_with_its_recipe():
    from pipelines.training.config import TrainConfig

    saved = {**TrainConfig(stage="detector", store="s.zarr", out="o", recipe="paper").to_dict()}
    saved["profile"] = saved.pop("recipe")
    assert TrainConfig.from_dict(saved).recipe == "paper"
