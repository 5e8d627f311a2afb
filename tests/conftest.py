import os
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import pytest

os.environ.setdefault("RAY_AUTH_MODE", "disabled")
os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
if os.environ.get("PYTEST_XDIST_WORKER"):  # `make test` runs one worker per core: one thread each, children too
    os.environ.setdefault("OMP_NUM_THREADS", "1")
if "RADARSEG_INT8_CACHE" not in os.environ:  # int8 calibrations kept by the suite's runs stay in the suite's folder
    os.environ["RADARSEG_INT8_CACHE"] = tempfile.mkdtemp(prefix="radarseg-int8-cache-")


def pytest_configure(config):
    if os.environ.get("PYTEST_XDIST_WORKER"):
        import torch

        torch.set_num_threads(1)


def pytest_collection_modifyitems(config, items):
    """Under pytest-xdist (``--dist loadgroup``) every test that starts a Ray cluster runs on one worker, so
    one cluster at a time shares the machine with the other workers' tests."""
    for item in items:
        if item.get_closest_marker("ray"):
            item.add_marker(pytest.mark.xdist_group("ray"))


@pytest.fixture(scope="session")
def small_recording(tmp_path_factory):
    """A tiny simulated recording (small preset, 2 sequences x 3 frames) shared by reader tests."""
    from pipelines.datasets.record import simulate_recording

    out = tmp_path_factory.mktemp("rec") / "small"
    return simulate_recording(preset="small", sequences=2, frames=3, seed=11, out=out, progress=False)


TINY_CLASSES = ("background", "pedestrian", "cyclist", "car")
UNTRAINED_NORMALISATION = {"mean": 60.0, "std": 8.0}
KINDS = {  # key -> (registered model, builder config, stage)
    "detector": ("centre_detector_tiny", {}, "detector"),
    "detector_history": ("centre_detector_tiny", {"history_frames": 1}, "detector"),  # reads the frame before
    "segmenter": ("minkunet_tiny", {}, "segmenter"),
    "unet_rd": ("unet_tiny", {"view": "rd"}, "baseline"),
    "unet_ra": ("unet_tiny", {"view": "ra"}, "baseline"),
    "tmvanet": ("tmvanet_tiny", {}, "baseline"),
    "smvanet": ("smvanet_tiny", {}, "baseline"),
}


def save_tiny_checkpoints(store, root, kinds=tuple(KINDS), *, mixed_labels: bool = True) -> dict[str, str]:
    """The one factory of untrained tiny checkpoints (small preset, seed 0), saved as the trainers save them.

    With a ``store`` the input normalisation (and the baselines' view scaling) are the store's, otherwise
    fixed values (no baseline then). With ``mixed_labels`` the segmenter's classifier never picks
    background, so its untrained labels mix the object classes inside every ROI."""
    import torch

    from models.checkpoint import Checkpoint, save_checkpoint
    from models.registry import create_model

    normalisation, stats = dict(UNTRAINED_NORMALISATION), None
    if store is not None:
        from pipelines.datasets.store import open_store
        from pipelines.datasets.views import ViewStats

        attrs = open_store(store).attrs
        normalisation = {"mean": float(attrs["normalisation"]["mean"]), "std": float(attrs["normalisation"]["std"])}
        stats = ViewStats.from_store(store, "train").to_dict()
    torch.manual_seed(0)
    made = {}
    for key in kinds:
        name, config, stage = KINDS[key]
        if stage == "baseline" and stats is None:
            raise ValueError(f"a tiny {key} needs a store for its view scaling")
        config = {"preset": "small", **config}
        model = create_model(name, **config)
        if key == "segmenter" and mixed_labels:
            with torch.no_grad():
                model.classifier.linear.bias.copy_(torch.tensor([-1e3, 0.0, 0.0, 0.0]))
        made[key] = save_checkpoint(Checkpoint(model_name=name, config=config, state_dict=model.state_dict(),
                                               preset="small", class_names=TINY_CLASSES,
                                               normalisation=stats if stage == "baseline" else normalisation,
                                               extra={"stage": stage}), Path(root) / f"{key}.pt")
    return {key: str(path) for key, path in made.items()}


@pytest.fixture(scope="session")
def tiny_checkpoints(tmp_path_factory) -> tuple[Path, Path]:
    """Random-weight tiny detector and MinkUNet for the small preset (fixed seed, no store)."""
    made = save_tiny_checkpoints(None, tmp_path_factory.mktemp("ckpt"), ("detector", "segmenter"), mixed_labels=False)
    return Path(made["detector"]), Path(made["segmenter"])


def wait_until(ready: Callable[[], bool], *, timeout_s: float, what: str, errors=(OSError,)) -> None:
    """Poll ``ready()`` every 0.5 s (``errors`` count as not ready yet) until it is true; RuntimeError naming
    ``what`` after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            if ready():
                return
        except errors:
            pass
        if time.monotonic() > deadline:
            raise RuntimeError(f"{what} within {timeout_s:g} s")
        time.sleep(0.5)
