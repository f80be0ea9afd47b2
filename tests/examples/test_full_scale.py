"""Full-scale runs (minutes): `./run-tests -m slow`."""

import json
import subprocess
import sys
from pathlib import Path

import pytest
from effect_networks.experiments.throwing import ThrowingConfig, run_throwing

ROOT = Path(__file__).resolve().parents[2]

pytestmark = pytest.mark.slow


def test_throwing_at_full_scale_beats_one_centimetre():
    result = run_throwing(ThrowingConfig(progress=False))
    assert result.rms_y_m < 0.010 and result.rms_z_m < 0.010
    assert result.rms_y_m < result.rms_y_m_single_gaussian


def test_reproduce_quick_writes_every_result(tmp_path):
    out, data = tmp_path / "results", tmp_path / "data"
    code = subprocess.call(
        [sys.executable, str(ROOT / "examples" / "reproduce.py"), "--quick"]
        + ["--out", str(out), "--data-dir", str(data)]
    )
    assert code == 0
    names = ("throwing.json", "can_tossing.json", "combined.json", "active.json")
    for name in (*names, "summary.md", "run.json"):
        assert (out / name).exists(), name
    combined = json.loads((out / "combined.json").read_text())
    assert set(combined["scenarios"]) == {"top_three", "near_flank", "far_flank"}
    summary = (out / "summary.md").read_text()
    assert summary.startswith("Scale: quick.") and "| total |" in summary
    assert summary.count("Table I exact") == 2
