"""examples/throwing.py runs end to end with tiny arguments."""

import json

import torch

from tests.helpers import load_example


def test_throwing_example_runs_and_writes_its_results(tmp_path):
    threads = torch.get_num_threads()
    summary = load_example("throwing").main(
        ["--n-train", "600", "--n-test", "60", "--bins", "1", "3", "--seed", "3"]
        + ["--out", str(tmp_path)]
    )
    assert torch.get_num_threads() == threads  # main leaves the thread count as it was
    saved = json.loads((tmp_path / "throwing.json").read_text())
    assert saved == json.loads(json.dumps(summary))
    for key in (
        "n_train",
        "n_test",
        "n_clusters",
        "rms_y_m",
        "rms_z_m",
        "rms_y_m_single_gaussian",
        "rms_z_m_single_gaussian",
        "rms_y_m_noisy",
        "rms_z_m_noisy",
        "noise_scatter_y_m",
        "noise_scatter_z_m",
        "cluster_selection",
        "timings_s",
    ):
        assert key in saved, key
    assert (saved["n_train"], saved["n_test"]) == (600, 60)
    assert saved["n_clusters"] in (1, 9)
    assert [row["bins"] for row in saved["cluster_selection"]] == [1, 3]
    assert (tmp_path / "throwing_errors.png").stat().st_size > 10_000
