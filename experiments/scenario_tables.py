"""The combined system's scenarios as the paper's Tables II-IV, in Markdown.

One scenario's result (:func:`experiments.combined.run_scenario`) as the paper's round
table (cans to throw, actions, successes, the three failures and the intermediate goals
per round), then the exact planner: measured beside predicted success, and its first
throw's equally rated fields and arrival, and that throw's next state as the models predict
and as the physics plays it (:func:`experiments.arrival_transfer.transfer_markdown`).
"""

from __future__ import annotations

from effect_networks.experiments.arrival_transfer import transfer_markdown

__all__ = ["TABLES", "table_markdown"]

#: Each scenario's table in the paper.
TABLES = {"top_three": "Table II", "near_flank": "Table III", "far_flank": "Table IV"}


def table_markdown(name: str, s: dict) -> str:
    """Scenario ``name``'s rounds in the paper's table format, and the exact planner."""
    rows = s["rounds"]
    head = "| round | " + " | ".join(str(i + 1) for i in range(len(rows))) + " |"
    lines = [
        f"**{TABLES[name]}: {name.replace('_', ' ')}** (paper: {100 * s['paper_success_rate']:.2f} %)",
        "",
        head,
        "|---" * (len(rows) + 1) + "|",
    ]
    for key, label in (
        ("cans_to_throw", "cans to throw"),
        ("actions", "actions"),
        ("success", "success (i)"),
        ("fail_too_many", "fail (ii)"),
        ("fail_no_hit", "fail (iii)"),
    ):
        lines.append(f"| {label} | " + " | ".join(str(r[key]) for r in rows) + " |")
    inter = [", ".join(f"{k} ({t})" for t, k in r["intermediate"].items()) or "-" for r in rows]
    lines.append("| interm. (iv) | " + " | ".join(inter) + " |")
    lines.append(
        "| success rate | " + " | ".join(f"{100 * r['success_rate']:.2f} %" for r in rows) + " |"
    )
    lines.append("")
    lines.append(
        f"Exact planner: {100 * s['success_rate_exact_planner']:.1f} % measured "
        f"({100 * s['exact_planner_predicted']:.1f} % predicted by the models"
        + (
            f"; {100 * s['exact_planner_predicted_sharp']:.1f} % with sharp field boundaries)."
            if "exact_planner_predicted_sharp" in s
            else ")."
        )
    )
    if "first_field_ties" in s:
        ties = s["first_field_ties"] - 1
        lines.append(
            f"Its first field, {s['exact_planner_first_field']}, rated equal with {ties} other "
            f"field(s) by the models; the robot's throw there arrives at "
            f"{s['first_throw_deg']:.1f} deg, {s['first_throw_speed']:.2f} m/s."
        )
    if "transfer" in s:
        arrival = (s["first_throw_deg"], s["first_throw_speed"])
        lines += ["", transfer_markdown(s["transfer"], arrival)]
    return "\n".join(lines)
