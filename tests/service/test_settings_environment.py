"""Every environment variable the service reads goes through its Settings: OMP_NUM_THREADS, and the variables the
models layer reads (the ONNX cache, its key file, the sparse kernels), which the app exports from its settings."""

from __future__ import annotations

import os

from service.main import create_app
from service.settings import Settings


def test_omp_num_threads_is_a_setting(monkeypatch):
    monkeypatch.setenv("OMP_NUM_THREADS", "3")
    assert Settings().omp_num_threads == 3 and Settings().inference_threads == 3
    assert Settings(torch_threads=2).inference_threads == 2
    assert Settings(omp_num_threads=5).inference_threads == 5


def test_the_models_layers_variables_come_from_the_settings(monkeypatch, tmp_path):
    for name in ("RADARSEG_ONNX_CACHE", "RADARSEG_ONNX_CACHE_KEY_FILE", "RADARSEG_SPARSE_KERNELS"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("RADARSEG_ONNX_CACHE", str(tmp_path / "from-env"))
    assert Settings().onnx_cache == tmp_path / "from-env"
    settings = Settings(onnx_cache=tmp_path / "cache", onnx_cache_key_file=tmp_path / "key", data_dir=tmp_path)
    create_app(settings)
    assert os.environ["RADARSEG_ONNX_CACHE"] == str(tmp_path / "cache")
    assert os.environ["RADARSEG_ONNX_CACHE_KEY_FILE"] == str(tmp_path / "key")
    assert "RADARSEG_SPARSE_KERNELS" not in os.environ


def test_the_service_reads_no_environment_outside_its_settings():
    from pathlib import Path

    root = Path(__file__).resolve().parents[2] / "service"
    readers = [str(p.relative_to(root)) for p in root.rglob("*.py") if "os.environ.get" in p.read_text()
               or "getenv(" in p.read_text() or "os.environ[" in p.read_text()]
    assert readers == [], f"environment read outside service/settings.py: {readers}"
