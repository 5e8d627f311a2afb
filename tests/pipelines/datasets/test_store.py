"""The store schema, its reader and the training Dataset, on a store built without Ray (fast)."""

import json

import numpy as np
import pytest
import torch
import zarr

from models.detector.targets import render_heatmap
from pipelines.cli import main as cli_main
from pipelines.datasets.store import (
    OBJECT_FIELDS,
    SPLIT_CODE,
    StoreDataset,
    StoreLayout,
    array_checksums,
    create_store,
    flip_angle,
    format_summary,
    open_store,
    summarise,
)
from radar.errors import DataError
from radar.instances import instance_stats
from radar.profiles import get_profile
from radar.simulate import SIMULATOR_VERSION, SimulatorConfig
from tests.pipelines.conftest import assert_store_matches_simulator

COL = {name: i for i, name in enumerate(OBJECT_FIELDS)}
SMALL = get_profile("small")


def test_store_holds_the_simulators_frames_and_targets(small_store):
    assert_store_matches_simulator(small_store, preset="small", sequences=2, frames=3, seed=5)


def test_schema_attributes_and_encoding(small_store):
    root = open_store(small_store)
    attrs = root.attrs.asdict()
    assert attrs["complete"] is True
    assert attrs["class_names"] == ["background", "pedestrian", "cyclist", "car"]
    assert attrs["radar"]["shape"] == [128, 128, 32]
    assert attrs["object_fields"] == list(OBJECT_FIELDS)
    assert attrs["job"]["seed"] == 5 and attrs["code_version"]["package"] == "0.1.0"
    assert attrs["simulator"] == SimulatorConfig().stamp() and attrs["simulator"]["version"] == SIMULATOR_VERSION
    inp = root["input"]
    assert inp.dtype == np.float16 and inp.shape == (6, 128, 128, 32)
    sharding = inp.metadata.codecs[0]
    assert isinstance(sharding, zarr.codecs.ShardingCodec)
    assert sharding.chunk_shape == (1, 128, 128, 32) and inp.shards == (2, 128, 128, 32)
    # log power byte-shuffled before zstd (its exponent bytes compress), labels plain zstd
    assert any(isinstance(c, zarr.codecs.BloscCodec) and c.cname.value == "zstd" and c.clevel == 1
               and c.shuffle.value == "shuffle" and c.typesize == 2 for c in sharding.codecs)
    assert any(isinstance(c, zarr.codecs.ZstdCodec) and c.level == 1 for c in root["labels"].metadata.codecs[0].codecs)
    assert root["heatmap"].shape == (6, 32, 32) and root["objects"].shape == (6, 32, len(OBJECT_FIELDS))
    # split by sequence: first sequence train, second val
    np.testing.assert_array_equal(root["split"][:], [0, 0, 0, 1, 1, 1])
    # class voxel counts agree with the labels
    labels = root["labels"][:]
    counts = attrs["class_voxel_counts"]
    np.testing.assert_array_equal(counts["train"], np.bincount(labels[:3].ravel(), minlength=4))
    np.testing.assert_array_equal(counts["val"], np.bincount(labels[3:].ravel(), minlength=4))
    # normalisation statistics are those of the train frames' stored input
    train = root["input"][:3].astype(np.float64)
    norm = attrs["normalisation"]
    assert norm["frames"] == 3
    assert norm["mean"] == pytest.approx(train.mean(), rel=1e-9)
    assert norm["std"] == pytest.approx(train.std(), rel=1e-9)
    np.testing.assert_allclose(norm["std_per_doppler"], train.std(axis=(0, 1, 2)), rtol=1e-9)
    # one progress marker per shard, each a readable zarr group
    assert sorted(root["progress"].group_keys()) == ["shard_00000", "shard_00001", "shard_00002"]


def test_dataset_samples_and_normalisation(small_store):
    ds = StoreDataset(small_store, "train")
    assert len(ds) == 3
    sample = ds[1]
    assert sample["input"].shape == (32, 128, 128) and sample["input"].dtype == torch.float32
    assert sample["labels"].shape == (128, 128, 32) and sample["labels"].dtype == torch.uint8
    assert sample["heatmap"].shape == (1, 32, 32)
    assert sample["objects"].shape == (32, len(OBJECT_FIELDS)) and sample["frame"] == 1
    stacked = torch.stack([ds[i]["input"] for i in range(len(ds))])  # (3, D, R, A)
    np.testing.assert_allclose(stacked.mean(dim=(0, 2, 3)).numpy(), 0.0, atol=1e-3)
    np.testing.assert_allclose(stacked.std(dim=(0, 2, 3)).numpy(), 1.0, atol=1e-3)
    raw = StoreDataset(small_store, "val", normalise=False, fields=("input",))
    assert len(raw) == 3 and set(raw[0]) >= {"input", "objects", "n_objects", "frame"}
    root = open_store(small_store)
    np.testing.assert_array_equal(raw[0]["input"].numpy(), root["input"][3].astype(np.float32).transpose(2, 0, 1))
    assert len(StoreDataset(small_store, "test")) == 0
    with pytest.raises(ValueError, match="split must be one of"):
        StoreDataset(small_store, "training")
    with pytest.raises(ValueError, match="unknown fields"):
        StoreDataset(small_store, fields=("input", "cube"))
    with pytest.raises(IndexError):
        ds[3]


def test_dataloader_workers_read_the_store(small_store):
    loader = torch.utils.data.DataLoader(StoreDataset(small_store, None, fields=("input", "heatmap")),
                                         batch_size=2, num_workers=2)
    batches = list(loader)
    assert sum(len(b["frame"]) for b in batches) == 6
    assert batches[0]["input"].shape == (2, 32, 128, 128)


def test_angle_flip_mirrors_x_and_never_range(small_store):
    plain = StoreDataset(small_store, None)
    flipped = StoreDataset(small_store, None, flip_prob=1.0)
    A = SMALL.n_angle
    mirror = (A - np.arange(A)) % A  # new angle bin a' holds old bin (A - a') mod A
    checked_objects = 0
    for i in range(len(plain)):
        p, f = plain[i], flipped[i]
        assert f["flipped"] and not p["flipped"]
        np.testing.assert_array_equal(f["input"].numpy(), p["input"].numpy()[:, :, mirror])
        np.testing.assert_array_equal(f["labels"].numpy(), p["labels"].numpy()[:, mirror, :])
        np.testing.assert_array_equal(f["instances"].numpy(), p["instances"].numpy()[:, mirror, :])
        np.testing.assert_array_equal(f["ra_mask"].numpy(), p["ra_mask"].numpy()[:, mirror])
        np.testing.assert_array_equal(f["rd_mask"].numpy(), p["rd_mask"].numpy())  # no angle axis
        n = int(p["n_objects"])
        pt, ft = p["objects"].numpy()[:n], f["objects"].numpy()[:n]
        for name in ("range_bin", "doppler_bin", "y", "offset_range", "class_id", "n_voxels", "track_id", "vy"):
            np.testing.assert_array_equal(ft[:, COL[name]], pt[:, COL[name]])  # range never flips
        np.testing.assert_allclose(ft[:, COL["x"]], -pt[:, COL["x"]])
        np.testing.assert_allclose(ft[:, COL["vx"]], -pt[:, COL["vx"]])  # the lateral velocity mirrors with x
        np.testing.assert_allclose(ft[:, COL["angle_bin"]], A - pt[:, COL["angle_bin"]], atol=1e-4)
        cells = ft[:, COL["angle_bin"]] / 4
        np.testing.assert_allclose(ft[:, COL["offset_angle"]], cells - np.floor(cells), atol=1e-5)
        centres = ft[:, [COL["range_bin"], COL["angle_bin"], COL["doppler_bin"]]]
        np.testing.assert_allclose(f["heatmap"][0].numpy(), render_heatmap(centres, (128, 128)), atol=1e-6)
        # the flipped cubes' own statistics give the flipped table (objects clear of endfire bin 0)
        stats = instance_stats(f["instances"].numpy(), SMALL)
        for row in ft:
            k = int(row[COL["instance_id"]])
            if not (p["instances"].numpy()[:, 0, :] == k).any():
                assert stats.x[k] == pytest.approx(row[COL["x"]], abs=1e-3)
                assert stats.angle_bin[k] == pytest.approx(row[COL["angle_bin"]], abs=1e-3)
                checked_objects += 1
        # flipping twice gives the sample back
        back = flip_angle(f, SMALL)
        np.testing.assert_array_equal(back["input"].numpy(), p["input"].numpy())
        np.testing.assert_allclose(back["objects"].numpy()[:n], pt, atol=1e-4)
    assert checked_objects > 0


def test_random_flips_are_reproducible(small_store):
    a = [StoreDataset(small_store, None, flip_prob=0.5, seed=3)[i]["flipped"] for i in range(6)]
    b = [StoreDataset(small_store, None, flip_prob=0.5, seed=3)[i]["flipped"] for i in range(6)]
    assert a == b and any(a) and not all(a)


def test_summary_and_store_info_command(small_store, capsys):
    summary = summarise(small_store)
    assert summary["frames"] == {"train": 3, "val": 3, "test": 0}
    assert summary["complete"] and summary["shards"] == {"total": 3, "done": 3}
    assert summary["quarantined"] == []
    text = format_summary(summary)
    assert "train 3, val 3, test 0" in text and "mean" in text
    assert cli_main(["store", "info", str(small_store)]) == 0
    out = capsys.readouterr().out
    assert "train 3, val 3, test 0" in out and "quarantined: 0" in out
    assert f"simulator: version {SIMULATOR_VERSION} (" in out and "tdm_coupling True" in out
    assert cli_main(["store", "info", "--json", str(small_store)]) == 0
    assert json.loads(capsys.readouterr().out)["frames"]["val"] == 3


def test_incomplete_or_foreign_stores_are_refused(tmp_path, capsys):
    layout = StoreLayout(SMALL, n_frames=4, shard_frames=2)
    create_store(tmp_path / "s.zarr", layout, {"plan": {}})
    with pytest.raises(DataError, match="incomplete"):
        open_store(tmp_path / "s.zarr")
    with pytest.raises(DataError, match="incomplete"):
        StoreDataset(tmp_path / "s.zarr")
    assert summarise(tmp_path / "s.zarr")["complete"] is False
    zarr.open_group(str(tmp_path / "other.zarr"), mode="w")
    with pytest.raises(DataError, match="format"):
        open_store(tmp_path / "other.zarr")
    with pytest.raises(DataError, match="not a zarr store"):
        open_store(tmp_path / "nothing")
    assert cli_main(["store", "info", str(tmp_path / "nothing")]) == 2
    assert "not a zarr store" in capsys.readouterr().err


def test_checksums_see_any_change(small_store, tmp_path):
    import shutil

    copy = tmp_path / "copy.zarr"
    shutil.copytree(small_store, copy)
    assert array_checksums(copy) == array_checksums(small_store)
    zarr.open_group(str(copy), mode="r+")["labels"][0, 0, 0, 0] = 3
    changed = {k for k, v in array_checksums(copy).items() if v != array_checksums(small_store)[k]}
    assert changed == {"labels"}
    assert SPLIT_CODE == {"train": 0, "val": 1, "test": 2}
