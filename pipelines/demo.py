"""``make demo``: the end-to-end job on embedded defaults. For now: simulate a small recording, read
it back through the reader, draw RA and RD pictures of a few frames with their labels, and
preprocess the recording into a store with embedded local Ray (``radarseg store info`` summary)."""

from __future__ import annotations

import shutil
from pathlib import Path

from pipelines.figures import plot_frame_views
from pipelines.preprocess import PreprocessConfig
from pipelines.preprocess import main as preprocess
from pipelines.record import simulate_recording
from radar.io.recording import Recording


def run_demo(out: str | Path = "out/demo", *, preset: str = "small", sequences: int = 2, frames: int = 6,
             seed: int = 7, pictures: int = 4, store: bool = True) -> dict[str, object]:
    out = Path(out)
    rec_dir = out / "recording"
    store_dir = out / "store.zarr"
    for own_output in (rec_dir, store_dir):  # the demo's own output: start afresh each run
        if own_output.exists():
            shutil.rmtree(own_output)
    simulate_recording(preset=preset, sequences=sequences, frames=frames, seed=seed, out=rec_dir)
    recording = Recording(rec_dir)
    step = max(1, len(recording) // pictures)
    paths = []
    for i, frame in enumerate(recording.frames()):
        if i % step == 0 and len(paths) < pictures:
            paths.append(plot_frame_views(frame, out / f"{frame.sequence}_{frame.index:03d}.png"))
    result: dict[str, object] = {"recording": rec_dir, "pictures": paths, "frames": len(recording)}
    if store:
        preprocess(PreprocessConfig(source=f"recording:{rec_dir.absolute()}", out=str(store_dir.absolute()),
                                    shard_frames=4, progress=False))
        result["store"] = store_dir
    return result
