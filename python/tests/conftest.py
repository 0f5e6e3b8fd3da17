"""Shared fixtures: the bundled sample as a short video of gray PNG frames, and the Rust CLI's answer on it."""

import json
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

ROOT = Path(__file__).resolve().parents[2]
SHIFTS = [0, 2, 4, 6, 8, 10]  # pixels to the right per frame: the face moves, the tracker follows it


def sample_path() -> Path:
    p = Path(os.environ.get("HOLOFACE_SAMPLE", ROOT / ".cache/holoface/astronaut.png"))
    if not p.is_file():
        pytest.fail(f"bundled sample {p} missing: run `make setup` (make python-test does)")
    return p


@pytest.fixture(scope="session")
def clip(tmp_path_factory) -> Path:
    """A folder of gray PNG frames (lossless, so the CLI and Python read the same bytes)."""
    gray = np.asarray(Image.open(sample_path()).convert("L"))
    out = tmp_path_factory.mktemp("clip")
    for i, dx in enumerate(SHIFTS):
        frame = np.zeros_like(gray)
        frame[:, dx:] = gray[:, : gray.shape[1] - dx]
        Image.fromarray(frame).save(out / f"frame_{i:03d}.png")
    return out


@pytest.fixture(scope="session")
def cli_lines(clip, tmp_path_factory) -> list:
    """`holoface track --source clip` (the Rust CLI, local KRFWS): one JSON object per frame."""
    cli = Path(os.environ.get("HOLOFACE_CLI", ROOT / "target/debug/holoface"))
    if not cli.is_file():
        pytest.fail(f"Rust CLI {cli} missing: make python-test builds it")
    out = tmp_path_factory.mktemp("cli") / "track.jsonl"
    subprocess.run([str(cli), "track", "--source", str(clip), "--out", str(out)], cwd=ROOT, check=True,
                   capture_output=True)
    return [json.loads(line) for line in out.read_text().splitlines()]
