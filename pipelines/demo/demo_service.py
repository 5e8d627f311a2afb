"""The demo's last step: start the service on loopback, post a simulated cube with an ordinary HTTP
client, and stop the service (by its process id)."""

from __future__ import annotations

import io
import os
import subprocess
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from pipelines.demo.serve_process import free_port, serve_command, stop_process, wait_ready
from radar.simulate import simulate_sequence


def post_to_service(out: Path, *, detector: Path, segmenter: Path, seed: int = 99,
                    ready_timeout_s: float = 300.0) -> dict[str, Any]:
    """``radarseg serve`` with the given checkpoints on a free loopback port; one simulated ``small`` cube
    posted to ``/v1/segment``; returns the response's objects, compute and usage, and the true objects."""
    port = free_port()
    env = {**os.environ, "RADARSEG_DATA_DIR": str((out / "service").absolute()),
           "RADARSEG_MODELS": f'[{{"name": "small", "detector": "{detector.absolute()}", '
                              f'"segmenter": "{segmenter.absolute()}"}}]'}
    log_path = out / "service.log"
    with log_path.open("w") as log:
        server = subprocess.Popen(serve_command(port), stdout=log, stderr=subprocess.STDOUT, env=env)
        try:
            url = f"http://127.0.0.1:{port}"
            wait_ready(url, server, log_path, timeout_s=ready_timeout_s)
            frame = next(simulate_sequence("small", 1, seed=seed))
            body = io.BytesIO()
            np.save(body, frame.cube, allow_pickle=False)
            response = httpx.post(f"{url}/v1/segment", content=body.getvalue(), timeout=120,
                                  headers={"content-type": "application/x-npy"})
            response.raise_for_status()
            answer = response.json()
        finally:
            stop_process(server)
    truth = [{"class_name": o.class_name, "x": o.centre_x, "y": o.centre_y} for o in frame.objects if o.n_voxels]
    return {"url": url, "objects": answer["objects"], "compute": answer["compute"], "usage": answer["usage"],
            "truth": truth}


def format_service_answer(answer: dict[str, Any]) -> str:
    lines = [f"POST {answer['url']}/v1/segment (a simulated small cube, 4 MiB .npy):"]
    for o in answer["objects"]:
        lines.append(f"  {o['class_name']:>10}  score {o['score']:.2f}  x {o['x']:6.1f} m  y {o['y']:6.1f} m  "
                     f"v {o['velocity_mps']:5.1f} m/s  voxels {o['n_voxels']}")
    lines.append("  simulated truth: " + ", ".join(f"{t['class_name']} at ({t['x']:.1f}, {t['y']:.1f}) m"
                                                   for t in answer["truth"]))
    c = answer["compute"]
    lines.append(f"  compute: {c['macs']['total'] / 1e9:.3f} GMACs (detect {c['macs']['detect'] / 1e9:.3f}, "
                 f"segment {c['macs']['segment'] / 1e9:.3f}), {c['roi_voxels']} ROI voxels, "
                 f"{c['visited_points']} visited, {c['seconds']['total'] * 1e3:.0f} ms")
    u = answer["usage"]
    lines.append(f"  usage today ({u['tenant']}): {u['requests']} requests, {u['macs'] / 1e9:.3f} GMACs")
    lines.append("see it in a browser: start the service with `.venv/bin/radarseg serve` and open "
                 "http://127.0.0.1:8000/viewer?example=1")
    return "\n".join(lines)
