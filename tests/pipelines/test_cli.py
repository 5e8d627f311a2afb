import json

import pytest

from pipelines.cli import main
from pipelines.demo.demo import run_demo


def test_simulate_writes_the_documented_layout(tmp_path, capsys):
    out = tmp_path / "rec"
    code = main(["simulate", "--preset", "small", "--sequences", "2", "--frames", "2", "--seed", "4",
                 "--out", str(out)])
    assert code == 0
    meta = json.loads((out / "recording.json").read_text())
    assert meta["sequences"] == {"seq_000": 2, "seq_001": 2}
    assert meta["source"]["seed"] == 4
    for seq in ("seq_000", "seq_001"):
        assert sorted(p.name for p in (out / seq / "cubes").iterdir()) == ["000000.npy", "000001.npy"]
        assert sorted(p.name for p in (out / seq / "labels").iterdir()) == ["000000.npz", "000001.npz"]
        assert len(json.loads((out / seq / "objects.json").read_text())["frames"]) == 2
    assert str(out) in capsys.readouterr().out


def test_cli_errors_are_one_clear_line(tmp_path, capsys):
    out = tmp_path / "rec"
    assert main(["simulate", "--sequences", "1", "--frames", "1", "--out", str(out)]) == 0
    assert main(["simulate", "--sequences", "1", "--frames", "1", "--out", str(out)]) == 2
    assert "a recording already exists" in capsys.readouterr().err
    assert main(["simulate", "--sequences", "0", "--frames", "1", "--out", str(tmp_path / "x")]) == 2


@pytest.mark.slow
def test_the_demo_runs_every_step_and_shows_each_result(tmp_path):
    """Pictures of the simulated frames, the store, the shipped model's scores on every frame and the service's
    answer (the store in this process: Ray's start-up is make demo's, which test_readme_commands runs)."""
    result = run_demo(tmp_path / "demo", sequences=1, frames=2, pictures=2, in_process=True)
    assert len(result["pictures"]) == 2
    for path in result["pictures"]:
        assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and path.stat().st_size > 20_000
    assert (result["store"] / "zarr.json").is_file() and result["frames"] == 2
    segmentation = result["segmentation"]
    assert segmentation["frames"] == 2 and segmentation["report"].is_file()
    assert 0.0 <= segmentation["metrics"]["segmentation"]["RA"]["mIoU"] <= 1.0
    assert "objects" in result["service"]


def test_job_commands_hand_their_arguments_to_the_jobs_parsers(capsys):
    import pytest

    for command in ("preprocess", "train", "train-baseline", "evaluate", "segment-batch"):
        with pytest.raises(SystemExit) as exc:
            main([command, "--help"])
        assert exc.value.code == 0
        assert f"radarseg {command}" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        main(["simulate", "--out", "x", "--bogus"])
    assert "unrecognized arguments: --bogus" in capsys.readouterr().err


def test_serve_becomes_the_services_runner_and_refuses_a_busy_port_before_loading_models():
    import socket
    import subprocess
    import sys

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        proc = subprocess.run([sys.executable, "-m", "pipelines.cli", "serve", "--port", str(port)],
                              capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert str(port) in proc.stderr and "Traceback" not in proc.stderr
    assert "loaded" not in proc.stderr.lower()  # refused before any model was loaded


def test_demo_says_each_step_and_its_time(tmp_path):
    said: list[str] = []
    run_demo(tmp_path / "demo", sequences=1, frames=1, pictures=1, store=False, say=said.append, progress=False)
    assert said[0].startswith("1. simulating 1 sequences of 1 frames") and said[-1].startswith("  done in ")


def test_progress_is_plain_lines_without_carriage_returns_off_a_terminal():
    import io

    from pipelines.progress import PlainProgress

    stream = io.StringIO()
    for _ in PlainProgress(range(3), desc="evaluate test", unit="frame", stream=stream, every_s=0.0):
        pass
    text = stream.getvalue()
    assert "\r" not in text and text.splitlines()[-1].startswith("evaluate test: 3/3 frame (100 %)")


def test_version_and_every_option_shows_its_default(capsys):
    import argparse

    import pytest

    from pipelines.cli import build_parser
    from pipelines.jobs import DefaultsHelpFormatter

    with pytest.raises(SystemExit):
        main(["--version"])
    assert capsys.readouterr().out.startswith("radarseg ")
    formatter = DefaultsHelpFormatter("radarseg")

    def options(parser):
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for sub in action.choices.values():
                    yield from options(sub)
            elif action.option_strings and not isinstance(action, (argparse._HelpAction, argparse._VersionAction)):
                yield action

    for action in options(build_parser()):
        if action.help == argparse.SUPPRESS:  # a former name, read with a note that names the new one
            continue
        assert action.help, action.option_strings
        if action.default is not None and not isinstance(action.default, bool) and action.default != []:
            assert "default" in formatter._get_help_string(action), action.option_strings


def test_serve_serves_its_one_pair_on_the_runtime_named_the_int8_kernels_included(tiny_checkpoints, capsys):
    """``serve --runtime torch-int8`` hands the service a model it serves in the compiled int8 kernels; the former
    ``--engine onnx-int8`` still names its runtime, with a note."""
    from pipelines.cli import build_parser
    from pipelines.cli.service_commands import _served_model
    from service.settings import ModelSpec

    det, seg = (str(path) for path in tiny_checkpoints)
    for options, runtime in ((["--runtime", "torch-int8"], "torch-int8"), ([], "torch"),
                             (["--engine", "onnx-int8"], "onnx-int8")):
        args = build_parser().parse_args(["serve", "--detector", det, "--segmenter", seg, *options])
        assert ModelSpec(**_served_model(args)).runtime == runtime
    assert "--runtime onnx-int8" in capsys.readouterr().err
