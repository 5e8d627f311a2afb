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


@pytest.mark.parametrize("command", [["simulate", "--out", "rec"], ["models", "summary"]])
def test_the_radar_is_named_by_profile_and_its_former_name_still_reads_with_a_note(command, capsys):
    from pipelines.cli import build_parser

    parser = build_parser()
    new = parser.parse_args([*command, "--profile", "carrada"])
    assert capsys.readouterr().err == ""
    former = parser.parse_args([*command, "--preset", "carrada"])
    assert "note: --preset is now --profile: use --profile carrada" in capsys.readouterr().err
    assert vars(former) == vars(new) and new.profile in ("carrada", ["carrada"])
    helps = {action.dest: action.help for action in _subparser(parser, command)._actions}
    assert "profile" in helps and "preset" not in helps


def test_the_former_radar_name_reaches_the_preprocess_config():
    from pipelines.jobs import job_module, parse_config

    cfg = parse_config(job_module("pipelines.datasets.preprocess"), ["--source", "sim", "--out", "s.zarr",
                                                                     "--preset", "carrada"], "radarseg preprocess")
    assert cfg.preset == "carrada"


def _subparser(parser, command):
    for word in command:
        if word.startswith("--"):
            break
        parser = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction").choices[word]
    return parser
