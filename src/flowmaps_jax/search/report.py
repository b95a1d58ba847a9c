"""The search report: ``search.json`` and ``search.md`` from :func:`protocol.run_search` results
(one table per policy, then by horizon, by category and, with habits, by habit; docs/search.md).
"""

from __future__ import annotations

import json
import pathlib
import re

from flowmaps_jax.atomic_files import make_output_dir, write_file

POLICY_LABELS = {"most-probable": "most-probable first",
                 "greedy": "greedy probability per pixel",
                 "optimal": "optimal expected travel (exact DP)",
                 "nearest": "nearest table first"}
_MAIN = (("sr@1", "SR@1", 3), ("sr@2", "SR@2", 3), ("sr@3", "SR@3", 3), ("looks", "looks", 2),
         ("travel", "travel [px]", 1), ("spl", "SPL", 3))
_RATIOS = (("looks", "looks ÷ exact"), ("travel", "travel ÷ exact"), ("spl", "SPL ÷ exact"))
# Under the most-probable-first table (docs/search.md, "Reading it").
FLAT_PRIOR_NOTE = (
    "Most-probable first ignores distance: with a flat prior (uniform over the kind, or a model "
    "that falls back to it) it degenerates to nearest-first, which travels less than the exact "
    "posterior driven by the same policy. That is why flat priors can score *below* 1 in this "
    "table's travel ratios: the ratio compares priors under one policy, not policies (see "
    "the optimal and greedy tables for what a prior is worth).")


def _mean_se(stat: dict | None, digits: int) -> str:
    if not stat or stat.get("mean") is None:
        return "–"
    if stat.get("stderr") is None:
        return f"{stat['mean']:.{digits}f}"
    return f"{stat['mean']:.{digits}f} ± {stat['stderr']:.{digits}f}"


def _number(value: float | None, digits: int = 3) -> str:
    return "–" if value is None else f"{value:.{digits}f}"


def protocol_line(p: dict) -> str:
    """One sentence describing the protocol of a results dict."""
    times = (f"Δτ in {p['horizons']}" if p.get("horizons")
             else f"{p['times_per_env']} (τ, τ_q) draws per environment, τ ~ U{{0..T−2}}, "
                  "τ_q ~ U{τ+1..T−1}")
    return (f"{p['num_envs']} validation environments, {times}, every object queried: "
            f"{p['episodes']} episodes per row. Start: {p['start']}; look budget {p['budget']}; "
            f"p_miss {p['p_miss']}; FlowMaps' table probabilities "
            + ("read from its mixture weights (no sampling), the MLP rows' from "
               if p.get("table_method") == "weights" else "and the MLP rows' from ")
            + f"{p['num_samples']} samples per query (protocol-v2 assignment, least radius "
            f"{p['assign_tolerance']}); seed {p['seed']}."
            + (f" World: {p.get('world') or p.get('habits')}; the exact posterior is given the "
               f"object's last H = {p['history']} observations (fewer before τ = "
               f"{p['history'] - 1}), and each model row reads its own H maps."
               if "history" in p else ""))


def _row_line(name: str, part: dict, pick=lambda section: section["overall"]) -> str:
    """One row of a policy table; ``pick`` chooses the part of each summary (overall, or one
    group's entry: a habit section's parts are that entry already)."""
    o = pick(part["summary"])
    cells = [name] + [_mean_se(o.get(key), d) for key, _, d in _MAIN]
    cells += [_number(pick(part["ratio"]).get(key)) for key, _ in _RATIOS]
    if "expected_ratio" in part:
        cells.append(_number(pick(part["expected_ratio"]).get("travel")))
    return "| " + " | ".join(cells) + " |"


def _habit_tables(results: dict, header: list[str]) -> list[str]:
    """The "By habit" section: per habit (``results["habits"]``), one table per policy with
    the policy table's columns on that habit's episodes."""
    habits = results.get("habits") or {}
    if not habits:
        return []
    total = sum(h["episodes"] for h in habits.values())
    if len(habits) == 1:  # a one-habit world: the section would repeat the tables above
        return ["\n## By habit", f"\nEvery object follows the {next(iter(habits))} habit: the "
                "tables above are its tables."]
    lines = ["\n## By habit",
             "\nEach object follows one habit (flowsim.habits); each table is the policy table "
             "on the episodes of that habit's objects only, ratios to the exact posterior on "
             "the same episodes."]
    for habit, section in habits.items():
        lines.append(f"\n### habit: {habit} ({section['episodes']} of {total} episodes)")
        for policy in results["protocol"]["policies"]:
            lines += [f"\n#### {POLICY_LABELS[policy]}\n", "| " + " | ".join(header) + " |",
                      "|" + "---|" * len(header)]
            lines += [_row_line(name, parts[policy], pick=lambda part: part)
                      for name, parts in section["rows"].items()]
    return lines


def _group_table(rows: dict, policy: str, group: str, title: str, pick) -> list[str]:
    keys = []
    for entry in rows.values():
        for k in entry["policies"][policy]["summary"][f"by_{group}"]:
            if k not in keys:
                keys.append(k)
    if group == "horizon":
        keys.sort(key=int)
    lines = [f"\n### {POLICY_LABELS[policy]}: {title}\n", "| row | " + " | ".join(keys) + " |",
             "|---|" + "---|" * len(keys)]
    for name, entry in rows.items():
        part = entry["policies"][policy]
        lines.append(f"| {name} | " + " | ".join(pick(part, group, k) for k in keys) + " |")
    return lines


def _travel_ratio(part: dict, group: str, key: str) -> str:
    source = part.get("expected_ratio", part["ratio"])
    return _number(source[f"by_{group}"].get(key, {}).get("travel"))


def _sr1(part: dict, group: str, key: str) -> str:
    return _number((part["summary"][f"by_{group}"].get(key) or {}).get("sr@1", {}).get("mean"), 2)


def markdown_table(results: dict) -> str:
    """The results as Markdown (see the module doc)."""
    rows = results["rows"]
    policies = results["protocol"]["policies"]
    expected = "expected_ratio" in next(iter(rows.values()))["policies"][policies[0]]
    lines = ["# Object search with the predicted posterior\n", protocol_line(results["protocol"]),
             "\nMean ± standard error over episodes; ratios are a row's mean over the exact-"
             "posterior searcher's mean under the same policy (looks and travel: lower is better; "
             "SPL: higher)."
             + (" E[travel] ÷ exact averages over the exact posterior of where the object is "
                "instead of the rollout's draw." if expected else "")]
    header = ["row"] + [label for _, label, _ in _MAIN] + [label for _, label in _RATIOS]
    header += ["E[travel] ÷ exact"] if expected else []
    for policy in policies:
        lines += [f"\n## {POLICY_LABELS[policy]}\n", "| " + " | ".join(header) + " |",
                  "|" + "---|" * len(header)]
        lines += [_row_line(name, entry["policies"][policy]) for name, entry in rows.items()]
        if policy == "most-probable":
            lines.append("\n" + FLAT_PRIOR_NOTE)
    lines += _habit_tables(results, header)
    what = "E[travel] ÷ exact" if expected else "travel ÷ exact"
    lines.append("\n## By horizon Δτ and by category")
    for policy in policies:
        lines += _group_table(rows, policy, "horizon", f"{what} by horizon Δτ", _travel_ratio)
        lines += _group_table(rows, policy, "horizon", "SR@1 by horizon Δτ", _sr1)
        lines += _group_table(rows, policy, "category", f"{what} by category", _travel_ratio)
        lines += _group_table(rows, policy, "category", "SR@1 by category", _sr1)
    lines += ["\n## Prior mass on the tables of the object's kind\n", "| row | mass |", "|---|---|"]
    lines += [f"| {name} | {_mean_se(entry['kind_mass'], 3)} |" for name, entry in rows.items()]
    figures = results.get("figures") or []
    lines += ["\n## Figures\n", *(f"![{name}]({name})" for name in figures)] if figures else []
    return "\n".join(lines) + "\n"


def compact_json(results: dict) -> str:
    """Indented JSON with every {mean, stderr} pair and every list of numbers on one line."""
    text = json.dumps(results, indent=1, allow_nan=False)
    text = re.sub(r'\{\n\s*"mean": ([^,\n]+),\n\s*"stderr": ([^\n]+)\n\s*\}',
                  r'{"mean": \1, "stderr": \2}', text)
    return re.sub(r"\[\n\s*([-+0-9.e,\s]+?)\n\s*\]",
                  lambda m: "[" + ", ".join(v.strip() for v in m.group(1).split(",")) + "]", text)


def write_report(results: dict, out_dir: str | pathlib.Path) -> dict[str, pathlib.Path]:
    """Write ``search.json`` and ``search.md`` into out_dir (created); returns their paths."""
    out = make_output_dir("out_dir", out_dir, files=("search.json", "search.md"))
    paths = {"json": out / "search.json", "markdown": out / "search.md"}
    text = compact_json(results) + "\n"
    write_file(paths["json"], text, name="out_dir file")
    write_file(paths["markdown"], markdown_table(results), name="out_dir file")
    return paths
