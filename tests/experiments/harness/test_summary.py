"""experiments.harness.summary builds the results table from small fake results, and refreshes
the results table between its markers only."""

import dataclasses
import json

import pytest
from effect_networks.experiments.harness import summary
from effect_networks.experiments.harness.registry import experiment


def write_result(folder, name: str, content: dict) -> None:
    """Experiment ``name``'s result file holding ``content``, its other fields None."""
    cls = experiment(name).result
    path = experiment(name).result_file(folder)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({f.name: None for f in dataclasses.fields(cls)} | content))


def fake_results(folder):
    """The fields the summary reads, with easily recognised values."""
    files = {
        "run.json": {
            "scale": "quick",
            "commit": "abc1234+",
            "date": "2026-01-02 03:04 UTC",
            "machine": "2 cores, a test machine",
            "step_seconds": {"throwing": 6.25, "can_tossing": 100.0},
            "total_seconds": 106.25,
        },
        "throwing.json": {
            "paper_rms_y_m": 0.0178,
            "paper_rms_z_m": 0.0305,
            "rms_y_m": 0.0041,
            "rms_z_m": 0.0085,
            "n_clusters": 36,
            "rms_y_m_single_gaussian": 0.02,
            "rms_z_m_single_gaussian": 0.0532,
            "rms_y_m_noisy": 0.019,
            "rms_z_m_noisy": 0.025,
            "noise_scatter_y_m": 0.016,
            "noise_scatter_z_m": 0.022,
        },
        "can_tossing.json": {
            "rule": "aim",
            "paper": {"exact_fraction": 0.9043, "n_cases": 8603},
            "table_one": {
                "counts": {
                    "aim": {"exact_fraction": 0.8235, "n_cases": 102},
                    "index": {"exact_fraction": 0.70, "n_cases": 102},
                },
                "actions": {
                    "aim": {"exact_fraction": 0.9573, "n_cases": 13129},
                    "index": {"exact_fraction": 0.8914, "n_cases": 13129},
                },
            },
            "emulation": {
                "same_end_config": 0.96,
                "n_demonstrations": 300,
                "reference_same_end_config": 0.85,
            },
            "imitation": {
                "auc": 0.939,
                "auc_ordinary": 0.974,
                "aim_sigma": 0.5,
                "auc_pooled": 0.952,
                "auc_ordinary_pooled": None,
                "n_throws": 300,
                "bound": {
                    "auc": 0.913,
                    "auc_ordinary": 1.0,
                    "auc_pooled": 0.911,
                    "auc_ordinary_pooled": 1.0,
                    "repeats": 16,
                },
            },
        },
        "physics_bounds.json": {
            "table_one": {
                "counts": {
                    "exact_fraction_bound": 0.7794,
                    "exact_fraction_in_sample": 0.864,
                    "repeats": 8,
                },
                "actions": {
                    "exact_fraction_bound": 0.9612,
                    "exact_fraction_in_sample": 0.97,
                    "repeats": 8,
                },
            },
            "combined": {
                "0.75": {
                    name: {"success_bound": b, "success_in_sample": 1.0}
                    for name, b in (("top_three", 0.5), ("near_flank", 0.0), ("far_flank", 0.0))
                }
            },
        },
        "combined.json": {
            "angle_choice": {"table_z": 0.75},
            "scenarios": {
                name: {
                    "paper_success_rate": 0.5713,
                    "success_rate": 0.2,
                    "success_rate_exact_planner": 0.9,
                    "exact_planner_predicted": 0.45,
                }
                for name in ("top_three", "near_flank", "far_flank")
            },
        },
    }
    files["tap_and_remove.json"] = {"rms_m": {"no parameter site": 0.2964}}
    (folder / "run.json").write_text(json.dumps(files.pop("run.json")))
    for name, content in files.items():
        write_result(folder, name.removesuffix(".json"), content)


def test_summary_from_fake_results(tmp_path):
    fake_results(tmp_path)
    text = summary.summary_markdown(tmp_path)
    head = text.splitlines()[0]
    assert head == (
        "Scale: quick. Commit: abc1234+. Date: 2026-01-02 03:04 UTC. "
        "Machine: 2 cores, a test machine."
    )
    assert "| 0.0178 / 0.0305 | 0.0041 / 0.0085 (36 clusters;" in text
    assert "no parameter site 0.2964 m" in text
    # Table I under both protocols, ours beside the bound
    counts = next(line for line in text.splitlines() if "reachable desired count" in line)
    assert "82.35 % of 102 (tie-break index: 70.00 %)" in counts
    assert "77.94 % held out, 86.40 % in sample (8 repeats)" in counts
    actions = next(line for line in text.splitlines() if "count-changing action" in line)
    assert "95.73 % of 13,129" in actions and "96.12 % held out" in actions
    assert "90.43 % of 8,603" in actions
    assert "0.952 / n/a" in text  # a missing AUC is said so
    # imitation beside its physics bound, ours as a fraction of it
    assert "0.913 / 1.000; aim-pooled 0.911 / 1.000" in text and "102.8 % / 97.4 % of it" in text
    top = next(line for line in text.splitlines() if "Table II" in line)
    assert "20.00 % (paper planner); 90.0 % (exact planner, predicted 45.0 %) | 50.0 % held" in top
    assert "| throwing | 6.2 | - | - | - |" in text and "| total | 106.2 | - | - | - |" in text
    assert "Goals:" not in text  # a record without the measures states none
    assert summary.write_summary(tmp_path).read_text() == text


def test_summary_of_missing_results_says_so(tmp_path):
    (tmp_path / "throwing.json").write_text("{}")
    (tmp_path / "throwing.json").unlink()
    text = summary.summary_markdown(tmp_path)
    assert text.startswith("Run: unknown")
    assert text.count("\n| ") == 1  # the table's head only


def test_refresh_results_replaces_only_the_block(tmp_path):
    readme = tmp_path / "README.md"
    readme.write_text(f"intro\n{summary.BEGIN}\nold\n{summary.END}\noutro\n")
    assert summary.refresh_results(readme, "new table\n")
    assert readme.read_text() == f"intro\n{summary.BEGIN}\nnew table\n{summary.END}\noutro\n"
    assert not summary.refresh_results(readme, "new table")
    readme.write_text("no markers\n")
    with pytest.raises(ValueError, match="needs one"):
        summary.refresh_results(readme, "x")


def test_run_record(tmp_path):
    record = summary.run_record("full", {"a": 1.5, "b": 2.0})
    assert record.total_seconds == 3.5 and record.scale == "full"
    assert "cores" in record.machine and "torch" in record.machine
    assert record.date.endswith("UTC") and record.commit
    record.save(tmp_path)
    assert summary.RunRecord.load(tmp_path / "run.json") == record


def test_every_goal_rows_state_both_planners_beside_the_bound(tmp_path):
    goal = {"bound": 0.5, "bound_in_sample": 0.75, "exact_measured": 0.25, "paper_measured": 0.0}
    other = {"bound": 1.0, "bound_in_sample": 1.0, "exact_measured": 1.0, "paper_measured": 0.5}
    table = {
        "table_z": 0.35,
        "reachable": 2,
        "exact_over_bound": 0.75,
        "paper_over_bound": 0.25,
        "goals": [goal, other],
    }
    result = {"settings": {"horizon": 6}, "goal_ratio": 0.9, "tables": [table]}
    write_result(tmp_path, "all_goals", result)
    (row,) = [r for r in summary.summary_markdown(tmp_path).splitlines() if "every goal" in r]
    assert "table 0.35 m, 2 goals" in row and "within 6 throws" in row
    assert "exact planner 62.5 % mean success, 75.0 % of the bound" in row
    assert "paper planner 25.0 %, 25.0 %" in row
    assert row.endswith("| 75.0 % mean held out, 87.5 % in sample |")


def test_active_rows_give_each_learner_at_ten_percent_beside_the_full_data(tmp_path):
    curve = {"aim": [0.5, 0.8, 0.9], "index": [0.4, 0.7, 0.8], "pooled": [0.6, 0.81, 0.9]}
    weak = {"aim": [0.1, 0.2, 0.3], "index": [0] * 3, "pooled": [0.15, 0.25, 0.35]}
    result = {
        "fractions": [0.05, 0.1, 0.2],
        "budgets": [50, 100, 200],
        "n_pool": 1000,
        "repeats": 16,
        "curves": {
            "eig": {"counts": curve, "actions": curve},
            "random": {"counts": curve, "actions": weak},
        },
        "full": {p: {"aim": 0.805, "index": 0.7, "pooled": 0.81} for p in ("counts", "actions")},
        "goal": {
            "eig": {p: {"aim": None, "index": None, "pooled": 100} for p in ("counts", "actions")},
            "random": {
                "counts": {"aim": None, "index": None, "pooled": 200},
                "actions": {"aim": None, "index": None, "pooled": None},
            },
        },
        "bound": {"counts": 0.77, "actions": 0.95},
    }
    write_result(tmp_path, "active", result)
    rows = [r for r in summary.summary_markdown(tmp_path).splitlines() if "active" in r]
    assert len(rows) == 2
    counts, actions = rows
    assert "reachable desired count" in counts and "10 % of the 1,000 0° throws" in counts
    assert (
        "eig 80.00 % (pooled 81.00 %), random 80.00 % (pooled 81.00 %); full data 80.50 % "
        "(pooled 81.00 %) (goal: within 1 point of the full data's best: eig)" in counts
    )
    assert "random 20.00 % (pooled 25.00 %)" in actions and actions.endswith("| 95.00 % held out |")


#: The adaptive-throw results' floor and active curves, the same in both layouts' tests.
THROW_FLOOR_AND_ACTIVE = {
    "floor": {"rms_y_m": 0.0003, "rms_z_m": 0.0004},
    "active": {
        "random": [{"n": 4000, "rms_y_m": 0.005, "rms_z_m": 0.006, "seeds_y_m": [0.0, 0.0]}],
        "information": [{"n": 4000, "rms_y_m": 0.004, "rms_z_m": 0.007}],
        "variance": [{"n": 4000, "rms_y_m": 0.0045, "rms_z_m": 0.0065}],
    },
    "active_floor": [{"n": 4000, "bins": 12, "rms_y_m": 0.0035, "rms_z_m": 0.0027}],
}


def test_adaptive_throw_rows(tmp_path):
    row = {"fit_s": 1.5, "em_steps": 7}
    layouts = [
        {"layout": layout, "n_clusters": k, "rms_y_m": y, "rms_z_m": z, **row}
        for layout, k, y, z in (
            ("grid", 4, 0.01, 0.01),
            ("adaptive", 4, 0.009, 0.009),
            ("grid", 256, 0.0021, 0.0020),
            ("adaptive", 256, 0.0018, 0.0013),  # an earlier EM checkpoint
            ("adaptive", 256, 0.0008, 0.0006),
        )
    ]
    write_result(
        tmp_path,
        "adaptive_throw",
        (
            {
                "layouts": layouts,
                "noisy": [
                    {"layout": "grid", "ratio_y": 1.15, "ratio_z": 1.15},
                    {"layout": "adaptive", "ratio_y": 1.05, "ratio_z": 1.10},
                ],
            }
            | THROW_FLOOR_AND_ACTIVE
        ),
    )
    text = summary.summary_markdown(tmp_path)
    assert (
        "(256 clusters, noise-free, posterior query; goal 0.01 cm, fit < 2 s) | - | "
        "adaptive 0.0800 / 0.0600 cm (fit 1.5 s, 7 EM steps), grid 0.2100 / 0.2000 cm "
        "(fit 1.50 s)" in text
    )
    assert "adaptive 1.05 / 1.10, grid 1.15 / 1.15 (goal 1.05)" in text
    assert "local Newton inverse of the training throws 0.0300 / 0.0400 cm |" in text
    assert (
        "after 4000 throws (mean of 2 seeds) | - | random 0.5000 / 0.6000 cm, information gain "
        "0.4000 / 0.7000 cm, variance (ALC) 0.4500 / 0.6500 cm | the same 12 x 12 grid fitted "
        "on all " in text
    )
    assert "training throws: 0.3500 / 0.2700 cm |" in text


def test_adaptive_throw_rows_with_both_queries(tmp_path):
    """Each layout by the inverse model, the posterior query beside it; the noisy ratios
    per row and the physics' bound."""
    layouts = [
        {"layout": layout, "query": query, "n_clusters": 256, "fit_s": 2.0, "em_steps": 5}
        | {"rms_y_m": y, "rms_z_m": z}
        for layout, query, y, z in (
            ("grid", "posterior", 0.0021, 0.0020),
            ("grid", "effect", 0.0012, 0.0017),
            ("adaptive", "posterior", 0.0012, 0.0006),
            ("adaptive", "effect", 0.00001, 0.0008),
        )
    ]
    layouts[-1] |= {"best_rms_y_m": 0.00002, "best_rms_z_m": 0.0002}
    noisy = [
        {"layout": layout, "query": query, "ratio_y": a, "ratio_z": b}
        for layout, query, a, b in (
            ("grid", "posterior", 1.15, 1.18),
            ("grid", "effect", 1.14, 1.17),
            ("adaptive", "posterior", 1.13, 1.16),
            ("adaptive", "effect", 1.08, 1.12),
        )
    ]
    write_result(
        tmp_path,
        "adaptive_throw",
        (
            {
                "layouts": layouts,
                "noisy": noisy,
                "noisy_bound": {"ratio_y": 1.07, "ratio_z": 1.10},
                "pieces": [
                    {"n_clusters": n, "rms_y_m": 0.0, "rms_z_m": z}
                    for n, z in ((64, 0.00045), (256, 0.00012))
                ],
            }
            | THROW_FLOOR_AND_ACTIVE
        ),
    )
    text = summary.summary_markdown(tmp_path)
    assert (
        "(256 clusters, noise-free, inverse model; goal 0.01 cm, fit < 2 s) | - | adaptive "
        "0.0010 / 0.0800 cm (fit 2.0 s, 5 EM steps; posterior query 0.1200 / 0.0600 cm; best "
        "of its candidates 0.0020 / 0.0200 cm), grid "
        "0.1200 / 0.1700 cm (fit 2.00 s; posterior query 0.2100 / 0.2000 cm)" in text
    )
    assert (
        "times the noise's own scatter: adaptive 1.08 / 1.12 (posterior query 1.13 / 1.16), "
        "grid 1.14 / 1.17 (posterior query 1.15 / 1.18) (goal 1.05)" in text
    )
    assert (
        "; one best plane per cell (unclamped) leaves 0.0000 / 0.0120 cm; with noise, the "
        "noise-free throw inverted: 1.07 / 1.10 |" in text
    )


def test_adaptive_throw_rows_show_the_goals_checkpoint_and_the_noisy_size(tmp_path):
    """The adaptive fit at its best checkpoint fitted in under 2 s (not its last, slower
    one), and the noisy comparison at its own cluster count."""
    layouts = [
        {"layout": layout, "query": query, "n_clusters": 400, "fit_s": fit_s, "em_steps": steps}
        | {"rms_y_m": y, "rms_z_m": z}
        for layout, query, fit_s, steps, y, z in (
            ("grid", "posterior", 0.02, 0, 0.001, 0.0012),
            ("grid", "effect", 0.02, 0, 0.0006, 0.0011),
            ("adaptive", "posterior", 1.4, 5, 0.00004, 0.00007),
            ("adaptive", "effect", 1.4, 5, 0.0, 0.00008),
            ("adaptive", "posterior", 5.0, 20, 0.0, 0.00006),
            ("adaptive", "effect", 5.0, 20, 0.0, 0.00005),
        )
    ]
    noisy = [
        {"layout": layout, "query": query, "n_clusters": 256, "ratio_y": 1.1, "ratio_z": 1.2}
        for layout in ("grid", "adaptive")
        for query in ("posterior", "effect")
    ]
    write_result(
        tmp_path,
        "adaptive_throw",
        (
            {"layouts": layouts, "noisy": noisy, "noisy_bound": {"ratio_y": 1.07, "ratio_z": 1.1}}
            | THROW_FLOOR_AND_ACTIVE
        ),
    )
    text = summary.summary_markdown(tmp_path)
    assert (
        "adaptive 0.0000 / 0.0080 cm (fit 1.4 s, 5 EM steps; posterior query 0.0040 / 0.0070 cm)"
        in text
    )
    assert "with release noise (256 clusters), times the noise's own scatter: adaptive 1.10" in text


def test_a_result_file_of_another_shape_is_named(tmp_path):
    (tmp_path / "throwing.json").write_text(json.dumps({"rms_y_m": 0.1}))
    with pytest.raises(ValueError, match=r"throwing\.json: not a ThrowingResult: the JSON lacks"):
        summary.summary_markdown(tmp_path)


def test_step_table_states_simulation_rest_and_peak_beside_the_goals(tmp_path):
    record = summary.run_record(
        "quick",
        {"throwing": 10.0, "active": 30.0},
        {"throwing": 9.5, "active": 2.0},
        {"throwing": 300_000_000, "active": 2_500_000_000},
    )
    record.save(tmp_path)
    text = summary.summary_markdown(tmp_path)
    assert "| throwing | 10.0 | 9.5 | 0.5 | 300 |" in text
    assert "| active | 30.0 | 2.0 | 28.0 | 2,500 |" in text
    assert "| total | 40.0 | 11.5 | 28.5 | 2,500 |" in text
    # rest 28.5 / 40 = 71.2 %; the largest process 2.5 GB, in active
    assert "at most 10 % of the total: 71.2 % (not met)" in text
    assert "under 2 GB: 2.50 GB, active (not met)" in text
    record = summary.run_record("quick", {"a": 10.0}, {"a": 9.5}, {"a": 10**9})
    record.save(tmp_path)
    text = summary.summary_markdown(tmp_path)
    assert "5.0 % (met)" in text and "1.00 GB, a (met)" in text


def test_a_run_record_without_the_measures_loads_with_them_empty(tmp_path):
    old = {
        "scale": "full",
        "commit": "abc",
        "date": "d",
        "machine": "m",
        "step_seconds": {"a": 1.0},
        "total_seconds": 1.0,
    }
    (tmp_path / "run.json").write_text(json.dumps(old))
    record = summary.RunRecord.load(tmp_path / "run.json")
    assert record.simulation_seconds == {} and record.peak_bytes == {}


def test_the_one_time_start_up_is_a_row_and_counts_in_the_total(tmp_path):
    """Imports done once before the steps: their own row (no simulation), in the total
    and in the rest; an older record without them loads with none."""
    record = summary.run_record("quick", {"a": 10.0}, {"a": 9.0}, {"a": 10**8}, 2.0)
    assert record.total_seconds == 12.0 and record.startup_seconds == 2.0
    record.save(tmp_path)
    assert summary.RunRecord.load(tmp_path / "run.json") == record
    text = summary.summary_markdown(tmp_path)
    assert "| start-up (imports, once) | 2.0 | 0.0 | 2.0 | - |" in text
    assert "| total | 12.0 | 9.0 | 3.0 | 100 |" in text
    assert "at most 10 % of the total: 25.0 % (not met)" in text  # 3 / 12
    old = json.loads((tmp_path / "run.json").read_text())
    del old["startup_seconds"]
    (tmp_path / "run.json").write_text(json.dumps(old))
    assert summary.RunRecord.load(tmp_path / "run.json").startup_seconds == 0.0
