"""The pipeline on a local Ray cluster (``python -m flowmimic.cluster``) with the tiny preset: every
stage runs as a task, its outputs are those of the single-machine pipeline, and a second run skips
every stage. Skipped where Ray is not installed."""

import json
import os
import pathlib
import struct
import subprocess

import pytest

ray = pytest.importorskip("ray", reason="ray is not installed: the cluster pipeline was not tested")

from flowmimic import cluster  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[2]


def binary() -> str:
    """The binary `cargo test` or `cargo build --release` made last (or $FLOWMIMIC_BIN)."""
    if os.environ.get("FLOWMIMIC_BIN"):
        return os.environ["FLOWMIMIC_BIN"]
    built = [p for p in (ROOT / "target" / b / "flowmimic" for b in ("release", "debug")) if p.exists()]
    if not built:
        pytest.skip("no flowmimic binary in target/: build it first (cargo build --release)")
    return str(max(built, key=lambda p: p.stat().st_mtime))


def tensors(path: pathlib.Path) -> bytes:
    """A safetensors file's tensor bytes (its header's metadata order may vary)."""
    data = path.read_bytes()
    return data[8 + struct.unpack("<Q", data[:8])[0] :]


def test_the_pipeline_on_a_local_ray_cluster_matches_one_machine(tmp_path, capsys):
    exe = binary()
    on_ray, alone = tmp_path / "ray", tmp_path / "alone"
    cluster.main(["pipeline", "--address", "local", "--workers", "2", "--preset", "tiny", "-o", str(on_ray), "--binary", exe])
    printed = capsys.readouterr().out
    for stage in ["clips", "expert:walk_straight", "rollouts:walk_straight", "collect", "train:fm", "train:ddpm", "evaluate"]:
        assert f"done {stage} in" in printed, printed
    assert (on_ray / "eval" / "report.md").exists()
    subprocess.run([exe, "--preset", "tiny", "pipeline", "-o", str(alone)], check=True, capture_output=True)
    # The same expert, rollouts and models, bit for bit.
    for file in [
        "experts/walk_straight/policy.safetensors",
        "data/walk_straight.rollouts.safetensors",
        "model/fm/model.safetensors",
        "model/ddpm/model.safetensors",
    ]:
        assert tensors(on_ray / file) == tensors(alone / file), f"{file} differs on the cluster"
    # The same manifest but for where the experts were, and the same summary.
    manifests = [json.loads((d / "data" / "manifest.json").read_text()) for d in (on_ray, alone)]
    for m in manifests:
        for shard in m["shards"]:
            shard.pop("expert")
    assert manifests[0] == manifests[1]
    inspect = [
        subprocess.run([exe, "dataset", "inspect", str(d / "data")], check=True, capture_output=True, text=True)
        .stdout.replace(str(d), "DIR")
        for d in (on_ray, alone)
    ]
    assert inspect[0] == inspect[1] and "walk_straight" in inspect[0]
    # Run again: every stage is done, each task skips it and says so; the logs keep both runs.
    cluster.main(["pipeline", "--address", "local", "--workers", "2", "--preset", "tiny", "-o", str(on_ray), "--binary", exe])
    assert capsys.readouterr().out.count("skipped ") == 7
    logs = sorted((on_ray / "logs").glob("*.log"))
    assert len(logs) == 7 and all(log.read_text().count("--- ") == 2 for log in logs)
    assert "steps" in (on_ray / "logs" / "expert-walk_straight.log").read_text(), "the training's log was lost"


def test_a_stage_that_fails_names_itself_and_its_log(tmp_path):
    with pytest.raises(SystemExit, match="is not an executable flowmimic binary"):
        cluster.main(["pipeline", "--address", "local", "-o", str(tmp_path), "--binary", str(tmp_path)])
    with pytest.raises(SystemExit) as stopped:
        cluster.main(
            ["pipeline", "--address", "local", "--workers", "1", "--preset", "tiny", "-o", str(tmp_path),
             "--binary", binary(), "--clip", str(tmp_path / "missing.bvh")]
        )
    message = str(stopped.value)
    assert "stage clips failed" in message and "clips.log" in message and "missing.bvh" in message, message
