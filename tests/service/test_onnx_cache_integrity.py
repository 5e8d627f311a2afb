"""The ONNX export cache the service's onnx engines load from: a cached graph edited after export is found by its
content hash and exported again (it loaded silently before and answered empty, billed), and an export planted by
someone who can write to a shared cache is neither found under a predictable name nor accepted under ours."""

from __future__ import annotations

import json
import logging

import pytest

from models.checkpoint import load_checkpoint
from models.export import export_cache
from models.export.export_cache import cache_secret, exported_dir, seal, seal_problem


@pytest.fixture
def pair(tiny_checkpoints, tmp_path, monkeypatch):
    monkeypatch.setenv(export_cache.CACHE_ENV, str(tmp_path / "cache"))
    monkeypatch.setenv(export_cache.KEY_FILE_ENV, str(tmp_path / "key"))
    return load_checkpoint(tiny_checkpoints[0]), load_checkpoint(tiny_checkpoints[1])


@pytest.mark.slow
def test_a_tampered_cached_graph_is_exported_again(pair, caplog):
    export = exported_dir(*pair)
    graph = export / "detector.onnx"
    original = graph.read_bytes()
    assert seal_problem(export, json.loads((export / "manifest.json").read_text())["seal"]["key"],
                        cache_secret()) is None
    tampered = original[:-64] + bytes(64)  # what an attacker's edit of the heatmap's weights amounts to
    graph.write_bytes(tampered)
    with caplog.at_level(logging.WARNING, logger="models.export.export_cache"):
        again = exported_dir(*pair)
    assert again == export and graph.read_bytes() != tampered
    assert "content differs from its manifest's hashes: detector.onnx" in caplog.text


@pytest.mark.slow
def test_an_export_planted_under_another_key_is_not_found_and_not_accepted(pair, tmp_path, monkeypatch):
    export = exported_dir(*pair)
    key = json.loads((export / "manifest.json").read_text())["seal"]["key"]
    seal(export, key, b"the attacker's own secret")  # a graph of theirs, sealed as well as they can
    assert seal_problem(export, key, cache_secret()) == "not sealed by this machine's cache key"
    monkeypatch.setenv(export_cache.KEY_FILE_ENV, str(tmp_path / "another-machine-key"))
    assert exported_dir(*pair).name != export.name  # another machine's folder name cannot be predicted


def test_an_unsealed_or_foreign_manifest_is_refused(tmp_path):
    (tmp_path / "manifest.json").write_text(json.dumps({"format": "x"}))
    (tmp_path / "detector.onnx").write_bytes(b"graph")
    assert seal_problem(tmp_path, "k", b"s") == "no content hashes in its manifest"
    seal(tmp_path, "k", b"s")
    assert seal_problem(tmp_path, "k", b"s") is None
    assert seal_problem(tmp_path, "other", b"s") == "built from other checkpoints or another recipe"
    (tmp_path / "segmenter.onnx").write_bytes(b"added later")
    assert "segmenter.onnx" in seal_problem(tmp_path, "k", b"s")
