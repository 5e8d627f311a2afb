"""The slimming sweep end to end on a tiny store with untrained tiny checkpoints: every model pruned at each
ratio (0 = the reference), fine-tuned for a step, scored, and the table, plot and JSON written."""

from __future__ import annotations

import json

import pytest

from models.checkpoint import load_checkpoint
from pipelines.jobs import parse_config
from pipelines.training import slim_sweep
from pipelines.training.slim_sweep import SweepConfig, main
from tests.pipelines.conftest import build_store_inline, save_tiny_checkpoints


@pytest.fixture(scope="module")
def sweep_inputs(tmp_path_factory):
    from pipelines.datasets.preprocess import PreprocessConfig

    root = tmp_path_factory.mktemp("sweep")
    store = build_store_inline(PreprocessConfig(source="sim", out=str(root / "seq.zarr"), preset="small", sequences=2,
                                                frames=4, seed=11, split_fractions=(0.5, 0.0, 0.5), shard_frames=4,
                                                progress=False))
    return store, save_tiny_checkpoints(store, root / "ckpt")


def test_sweep_prunes_finetunes_scores_and_reports(sweep_inputs, tmp_path):
    store, ckpt = sweep_inputs
    cfg = SweepConfig(store=str(store), out=str(tmp_path / "report"), work=str(tmp_path / "work"),
                      detector=ckpt["detector"], minkunet=ckpt["segmenter"], smvanet=ckpt["smvanet"], ratios=(0.3,),
                      max_frames=2, finetune_steps=1, batch_size=1)
    result = main(cfg, command="radarseg slim-sweep (test)")
    rows = {(r["model"], r["ratio"]): r for r in result["rows"]}
    assert set(rows) == {(kind, ratio) for kind in ("detector", "minkunet", "smvanet") for ratio in (0.0, 0.3)}
    for kind in ("detector", "minkunet", "smvanet"):
        before, after = rows[(kind, 0.0)], rows[(kind, 0.3)]
        assert after["params"] < before["params"], kind
        assert "pruned_mIoU_RA" in after or "pruned_mAP" in after, kind  # scored before and after fine-tuning
        rebuilt = load_checkpoint(after["checkpoint"]).build()  # a pruned checkpoint rebuilds on its own
        assert sum(p.numel() for p in rebuilt.parameters()) == after["params"], kind
    assert rows[("smvanet", 0.3)]["macs"] < rows[("smvanet", 0.0)]["macs"]
    assert 0.0 <= rows[("minkunet", 0.3)]["mIoU_RA"] <= 1.0 and 0.0 <= rows[("detector", 0.3)]["mAP"] <= 1.0
    report = (tmp_path / "report" / "slimming.md").read_text()
    assert "radarseg slim-sweep (test)" in report and "| 0.3 |" in report
    assert (tmp_path / "report" / "slimming.png").stat().st_size > 0
    assert len(json.loads((tmp_path / "report" / "slimming.json").read_text())["rows"]) == 6


def test_sweep_refuses_bad_settings(tmp_path):
    with pytest.raises(ValueError, match="ratios"):
        SweepConfig(store="s.zarr", ratios=(1.0,))
    with pytest.raises(ValueError, match="--detector"):
        SweepConfig(store="s.zarr", minkunet="m.pt")
    with pytest.raises(ValueError, match="at least one checkpoint"):
        main(parse_config(slim_sweep, ["--store", "s.zarr", "--out", str(tmp_path)], "radarseg slim-sweep"))
