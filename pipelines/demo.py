"""``make demo``: the end-to-end job on embedded defaults. Simulate a small recording, read it back
through the reader, draw RA and RD pictures of a few frames with their labels, preprocess the
recording into a store with embedded local Ray (``radarseg store info`` summary), then segment a few
test frames with the shipped model (``checkpoints/``): pictures with the ground truth beside the
prediction and a short metrics table (:func:`pipelines.evaluate.evaluate` on those frames)."""

from __future__ import annotations

import shutil
from pathlib import Path

from pipelines.figures import plot_frame_views
from pipelines.preprocess import PreprocessConfig
from pipelines.preprocess import main as preprocess
from pipelines.record import simulate_recording
from radar.io.recording import Recording

SHIPPED = Path(__file__).resolve().parents[1] / "checkpoints"


def run_demo(out: str | Path = "out/demo", *, preset: str = "small", sequences: int = 3, frames: int = 6,
             seed: int = 7, pictures: int = 4, store: bool = True, segment_frames: int = 4,
             checkpoints: str | Path = SHIPPED, service: bool = True, in_process: bool = False) -> dict[str, object]:
    out = Path(out)
    rec_dir = out / "recording"
    store_dir = out / "store.zarr"
    eval_dir = out / "segmentation"
    for own_output in (rec_dir, store_dir, eval_dir):  # the demo's own output: start afresh each run
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
        # with 3 sequences: one each for train / val / test (split by sequence, in name order)
        fractions = (0.5, 0.25, 0.25) if sequences >= 3 else None
        preprocess(PreprocessConfig(source=f"recording:{rec_dir.absolute()}", out=str(store_dir.absolute()),
                                    shard_frames=4, split_fractions=fractions, progress=False,
                                    in_process=in_process))
        result["store"] = store_dir
        checkpoints = Path(checkpoints)
        if segment_frames and (checkpoints / "detector.pt").is_file() and (checkpoints / "segmenter.pt").is_file():
            from pipelines.evaluate import EvaluateConfig, evaluate, format_summary
            from pipelines.store import frames_of_split, open_store

            # the test sequence's frames (every frame when the recording is too short to have one)
            split = "test" if len(frames_of_split(open_store(store_dir), "test")) else None
            metrics = evaluate(EvaluateConfig(
                detector=str(checkpoints / "detector.pt"), segmenter=str(checkpoints / "segmenter.pt"),
                store=str(store_dir), out=str(eval_dir), split=split, max_frames=segment_frames,
                pictures=segment_frames, sweep=(), sweep_frames=0, oracle=False, progress=False))
            result["segmentation"] = {"dir": eval_dir, "report": eval_dir / "report.md",
                                      "pictures": [eval_dir / name for name in metrics["pictures"]],
                                      "table": format_summary(metrics)}
            if service:
                from pipelines.demo_service import post_to_service

                result["service"] = post_to_service(out, detector=checkpoints / "detector.pt",
                                                    segmenter=checkpoints / "segmenter.pt")
    return result
