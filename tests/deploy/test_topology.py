"""The compose topology as processes on loopback: a Ray head and one worker joined to it, a preprocessing
job and a batch segmentation job submitted to the head (their work spread over both nodes), a resumed
batch job, and two API processes (uvicorn factory and ``radarseg serve``) sharing one PostgreSQL ledger;
then the Ray Serve deployment of deploy/serve.yaml with 2 replicas serving concurrent requests."""

from __future__ import annotations

import json
import re
import subprocess
import time
from concurrent.futures import ThreadPoolExecutor

import httpx
import numpy as np
import pytest
import yaml

from pipelines.datasets.store import open_store
from pipelines.inference.predictions_store import COMPUTE_FIELDS, open_predictions
from service.accounting.ledger import Ledger
from tests.deploy.conftest import radarseg_serve_command, submit_job, uvicorn_command
from tests.pipelines.conftest import BIN, REPO, free_port, ray_env
from tests.service.conftest import NPY, npy_bytes

pytestmark = [pytest.mark.slow, pytest.mark.ray]

KEY, TENANT = "key-deploy-0123456789abcdef", "acme"


def _models_json(tiny_checkpoints) -> str:
    det, seg = tiny_checkpoints
    return json.dumps([{"name": "tiny", "detector": str(det), "segmenter": str(seg), "score_threshold": 0.0,
                        "max_objects": 1}])


def test_cluster_runs_both_jobs_and_two_apis_share_the_ledger(cluster, tiny_checkpoints, postgres_url, pg_prefix,
                                                              api_processes, tmp_path):
    det, seg = tiny_checkpoints
    # The APIs start first: they load their models while the jobs run.
    env = {"RADARSEG_MODELS": _models_json(tiny_checkpoints), "RADARSEG_LEDGER_URL": postgres_url,
           "RADARSEG_LEDGER_TABLE_PREFIX": pg_prefix, "RADARSEG_API_KEYS": json.dumps({KEY: TENANT}),
           "RADARSEG_MAX_QUEUE": "8", "RADARSEG_DATA_DIR": str(tmp_path / "service")}
    ports = free_port(), free_port()
    apis = [api_processes(uvicorn_command(ports[0]), ports[0], env),
            api_processes(radarseg_serve_command(ports[1]), ports[1], env)]

    # 1. preprocessing submitted to the head: 4 one-frame shards as Ray tasks over both nodes
    store = tmp_path / "store.zarr"
    pre = submit_job(cluster, "pipelines.datasets.preprocess", "--source", "sim", "--preset", "small",
                     "--sequences", "2",
                     "--frames", "2", "--seed", "3", "--shard-frames", "1", "--split-fractions", "0.5", "0.5", "0",
                     "--no-progress", "--json", "--out", str(store))
    assert pre["written"] == 4 and pre["shards_run"] == 4, pre
    assert open_store(store).attrs["complete"]

    # 2. batch segmentation submitted to the head: one segmenter actor per node, each loading the model once
    predictions = tmp_path / "predictions.zarr"
    job = ["pipelines.inference.segment_batch", "--source", f"store:{store}", "--detector", str(det),
           "--segmenter", str(seg),
           "--out", str(predictions), "--workers", "2", "--shard-frames", "1", "--score-threshold", "0",
           "--max-objects", "2", "--no-progress", "--json"]
    result = submit_job(cluster, *job)
    assert (result["written"], result["shards_run"], result["workers"], result["nodes"]) == (4, 4, 2, 2), result
    assert [w["model_loads"] for w in result["worker_stats"]] == [1, 1]
    assert sum(w["shards"] for w in result["worker_stats"]) == 4 and result["frames_per_second"] > 0
    root = open_predictions(predictions)
    assert root["labels"].shape == (4, 128, 128, 32) and root["valid"][:].tolist() == [1, 1, 1, 1]
    macs_total = root["compute"][:, COMPUTE_FIELDS.index("macs_total")]
    assert (macs_total > 0).all() and int(macs_total.sum()) == result["macs_total"]
    assert root["source_slot"][:].tolist() == [0, 1, 2, 3]

    # 3. resume: a lost shard marker makes a rerun (a driver joined with --address) redo that shard only
    labels_before = root["labels"][:]
    (predictions / "progress" / "shard_00002" / "zarr.json").unlink()
    proc = subprocess.run([str(BIN / "python"), "-m", *job, "--address", cluster.gcs_address], cwd=REPO,
                          env=ray_env(), capture_output=True, text=True, timeout=180)
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-4000:]
    resumed = json.loads(proc.stdout.strip().splitlines()[-1])
    assert (resumed["shards_run"], resumed["shards_skipped"], resumed["written"]) == (1, 3, 4), resumed
    np.testing.assert_array_equal(open_predictions(predictions)["labels"][:], labels_before)

    # 4. cubes posted to both API processes; both read the same ledger totals
    from radar.simulate import simulate_sequence

    bodies = [npy_bytes(frame.cube) for frame in simulate_sequence("small", 2, seed=9)]
    for api in apis:
        api.wait_ready()
    headers = {**NPY, "X-API-Key": KEY}
    with httpx.Client(timeout=120) as http, ThreadPoolExecutor(4) as pool:
        answers = list(pool.map(lambda i: http.post(f"{apis[i % 2].url}/v1/segment", content=bodies[i % 2],
                                                    headers=headers), range(6)))
        assert all(a.status_code == 200 for a in answers), [a.text for a in answers if a.status_code != 200]
        macs = sum(a.json()["compute"]["macs"]["total"] for a in answers)
        for api in apis:
            usage = http.get(f"{api.url}/v1/usage", headers={"X-API-Key": KEY}).json()["tenants"][0]
            assert usage["tenant"] == TENANT and (usage["total"]["requests"], usage["total"]["macs"]) == (6, macs)
    ledger = Ledger(postgres_url, table_prefix=pg_prefix, pool_size=0)
    try:
        totals = ledger.day_totals(TENANT)
        assert (totals.requests, totals.macs, totals.reserved_macs) == (6, macs, 0)
    finally:
        ledger.dispose()


def _serve_config(tiny_checkpoints, port: int, ledger: dict[str, str]) -> dict:
    """deploy/serve.yaml with the test's settings: loopback, a fixed 2 replicas, the tiny model."""
    config = yaml.safe_load((REPO / "deploy" / "serve.yaml").read_text())
    config["proxy_location"] = "HeadOnly"  # one HTTP proxy: both nodes share this machine's ports
    config["http_options"].update(host="127.0.0.1", port=port)
    app = config["applications"][0]
    app["args"]["settings"] = {"models": json.loads(_models_json(tiny_checkpoints)), "host": "127.0.0.1", **ledger}
    deployment = app["deployments"][0]
    del deployment["autoscaling_config"]
    deployment.update(num_replicas=2, ray_actor_options={"num_cpus": 0.5})
    return config


def _serve_status(cluster) -> dict:
    with httpx.Client(timeout=10) as http:
        return http.get(f"{cluster.dashboard_url}/api/serve/applications/").json()


def _serve_cli(cluster, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([str(BIN / "serve"), *args, "--address", cluster.dashboard_url], cwd=REPO, env=ray_env(),
                          capture_output=True, text=True, timeout=120)


def test_ray_serve_two_replicas_serve_concurrent_requests(cluster, tiny_checkpoints, postgres_url, pg_prefix,
                                                          tmp_path):
    pytest.importorskip("ray.serve", reason="Ray Serve's dependencies (ray[serve]) are not installed")
    port = free_port()
    ledger = {"ledger_url": postgres_url, "ledger_table_prefix": pg_prefix}
    config_path = tmp_path / "serve.yaml"
    config_path.write_text(yaml.safe_dump(_serve_config(tiny_checkpoints, port, ledger)))
    deployed = _serve_cli(cluster, "deploy", str(config_path))
    assert deployed.returncode == 0, deployed.stdout + deployed.stderr
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 180
        while True:
            status = _serve_status(cluster).get("applications", {}).get("radarseg", {})
            if status.get("status") == "RUNNING":
                break
            assert status.get("status") not in ("DEPLOY_FAILED", "UNHEALTHY"), status
            assert time.monotonic() < deadline, f"Serve app not running within 180 s: {status}"
            time.sleep(1.0)
        replicas = status["deployments"]["radarseg"]["replicas"]
        assert len(replicas) == 2 and {r["state"] for r in replicas} == {"RUNNING"}, replicas
        assert httpx.get(f"{url}/readyz", timeout=10).status_code == 200

        from radar.simulate import simulate_sequence

        body = npy_bytes(next(simulate_sequence("small", 1, seed=4)).cube)
        with httpx.Client(timeout=120) as http, ThreadPoolExecutor(4) as pool:
            answers = list(pool.map(lambda _: http.post(f"{url}/v1/segment", content=body, headers=NPY), range(8)))
            assert [a.status_code for a in answers] == [200] * 8, [a.text for a in answers if a.status_code != 200]
            usage = http.get(f"{url}/v1/usage").json()["tenants"][0]["total"]
            assert usage["requests"] == 8
            assert usage["macs"] == sum(a.json()["compute"]["macs"]["total"] for a in answers)
            # Each replica is its own app with its own metrics: both served some of the 8 requests.
            counts = set()
            pattern = re.compile(r'radarseg_segment_requests_total\{model="tiny",tenant="anonymous"\} (\d+)')
            for _ in range(60):
                found = pattern.search(http.get(f"{url}/metrics").text)
                counts.add(int(found.group(1)) if found else 0)
                if any(a + b == 8 and a > 0 and b > 0 for a in counts for b in counts):
                    break
            assert any(a + b == 8 and a > 0 and b > 0 for a in counts for b in counts), counts
    finally:
        shutdown = _serve_cli(cluster, "shutdown", "--yes")
        assert shutdown.returncode == 0, shutdown.stdout + shutdown.stderr
