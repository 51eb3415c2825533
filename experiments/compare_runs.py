"""Are two runs' tables the same within their seed spread? ``python -m experiments.compare_runs
--reference RUNS... --candidate RUNS... [--out DIR]``.

Each side is one or more earlier runs of an experiment (their ``metrics.json`` or
``runs_partial.json``, joined as ``experiments.run --tables-from`` joins them), normally the
same experiment before and after a change that alters what is trained (e.g. shorter training
budgets, issue 32 item 3). Every quality value both sides record (ARI and the other clustering
scores, PCP, MPJPE, mAP and recall, completeness, IDF1, MOTA, ID switches per 1,000, jitter) is
averaged over each side's training seeds, and the difference of the means is compared with what
the seeds' spread allows: ``|mean_c - mean_r| <= 2 * sqrt(sd_r^2 / n_r + sd_c^2 / n_c)`` (twice
the standard error of the difference; sample standard deviations); the counts also say how many
differences are within one seed's sd (the larger side's). A value no seed moves (sd 0 on both
sides, e.g. triangulation on true groups) must be equal to rounding. Two sets of seeds of the
same code fail a 2-SE test now and then (about one value in twenty by design, more with three
seeds' noisy sds): read the list of values outside, not only its length. Timings, settings
and training curves are not compared.

Writes ``compare.md`` (the headline rows, every value outside the spread, the counts per split)
and ``compare.json`` into ``--out`` (default: prints the markdown).
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
from pathlib import Path

from experiments.records import RUN_SETTINGS, runs_from_files
from mvpose_jax.data.files import atomic_write_text

# The leaves compared: what a table reports about quality (not timings or settings).
QUALITY = frozenset(
    {
        "ari",
        "homogeneity",
        "completeness",
        "v_measure",
        "pooled_ari",
        "pooled_homogeneity",
        "pooled_completeness",
        "pooled_v_measure",
        "pcp",
        "mpjpe_mm",
        "map",
        "mean_recall",
        "idf1",
        "mota",
        "switches_per_1000",
        "jitter_mm",
    }
)
# Branches that hold sweeps or per-person lists rather than a table's values.
SKIPPED = ("training", "figures", "pcp_by_person", "pcp_by_limb")
# Rounding a value no seed moves may differ by (the reports round to 4 decimals).
EXACT_TOL = 1e-3

HEADLINE = (
    ("matching/test/2/gat_chosen/ari", "2-view GAT ARI, dev threshold"),
    ("matching/test/3/gat_chosen/ari", "3-view GAT ARI, dev threshold"),
    ("matching/test/5/gat_chosen/ari", "5-view GAT ARI, dev threshold"),
    ("matching/test/5/gat/ari", "5-view GAT ARI, threshold 0.5"),
    ("pose/test/detected/pipeline/ours/pcp", "Table 6 D-detected ours PCP"),
    ("pose/test/detected/pipeline/ours/mpjpe_mm", "Table 6 D-detected ours MPJPE mm"),
    ("pose/test/projected/pipeline/ours/mpjpe_mm", "Table 6 D-projected ours MPJPE mm"),
    ("pose/test/average/pipeline/ours/mpjpe_mm", "Table 6 D-average ours MPJPE mm"),
    ("pose/test/detected/pipeline/ours/map", "Table 6 D-detected ours mAP"),
    ("pose/test/detected/true_groups/ours/mpjpe_mm", "estimator alone, true groups, MPJPE mm"),
    ("tracking/test/learned/identity/idf1", "tracks: infer default IDF1"),
    ("tracking/test/learned/butterworth/mpjpe_mm", "tracks: infer default, Butterworth, MPJPE"),
    ("tracking/test/learned/butterworth/pcp", "tracks: infer default, Butterworth, PCP"),
)


def quality_values(run: dict) -> dict[str, float]:
    """A run's quality leaves by path ("pose/test/detected/pipeline/ours/pcp": 94.4)."""
    out: dict[str, float] = {}

    def walk(node, path):
        if isinstance(node, dict):
            for key, value in node.items():
                if key not in SKIPPED:
                    walk(value, (*path, str(key)))
        elif (
            path
            and path[-1] in QUALITY
            and isinstance(node, (int, float))
            and not isinstance(node, bool)
            and math.isfinite(node)
        ):
            out["/".join(path)] = float(node)

    walk(run, ())
    return out


def compare(reference: list[dict], candidate: list[dict]) -> list[dict]:
    """One row per quality value both sides record in every seed: means, sds, the difference
    and whether it lies within the seeds' spread (module docstring)."""
    ref = [quality_values(r) for r in reference]
    cand = [quality_values(r) for r in candidate]
    keys = sorted(set.intersection(*(set(v) for v in ref + cand)))
    rows = []
    for key in keys:
        a = [v[key] for v in ref]
        b = [v[key] for v in cand]
        sd_a = statistics.stdev(a) if len(a) > 1 else 0.0
        sd_b = statistics.stdev(b) if len(b) > 1 else 0.0
        mean_a, mean_b = statistics.fmean(a), statistics.fmean(b)
        allowed = 2.0 * math.sqrt(sd_a**2 / len(a) + sd_b**2 / len(b))
        diff = mean_b - mean_a
        rows.append(
            {
                "value": key,
                "split": key.split("/")[1] if key.count("/") >= 1 else "",
                "reference": mean_a,
                "reference_sd": sd_a,
                "candidate": mean_b,
                "candidate_sd": sd_b,
                "difference": diff,
                "allowed": allowed,
                "within": abs(diff) <= max(allowed, EXACT_TOL * max(1.0, abs(mean_a))),
                "within_one_sd": abs(diff) <= max(sd_a, sd_b, EXACT_TOL * max(1.0, abs(mean_a))),
            }
        )
    return rows


def _fmt(x: float) -> str:
    return f"{x:.4f}" if abs(x) < 10 else f"{x:.2f}"


def _line(row: dict, label: str | None = None) -> str:
    return (
        f"| {label or row['value']} | {_fmt(row['reference'])} ± {_fmt(row['reference_sd'])} | "
        f"{_fmt(row['candidate'])} ± {_fmt(row['candidate_sd'])} | {row['difference']:+.4f} | "
        f"{_fmt(row['allowed'])} | {'yes' if row['within'] else '**no**'} |"
    )


def markdown(rows: list[dict], reference: list[dict], candidate: list[dict], command: str) -> str:
    by_key = {r["value"]: r for r in rows}
    head = "| value | reference | candidate | difference | allowed (2 SE) | within |"
    rule = "|---|---|---|---|---|---|"
    lines = [
        "# Two runs' tables compared within their seed spread",
        "",
        f"Command: `{command}`.",
        f"Reference: training seeds {[r['seed'] for r in reference]}; candidate: "
        f"{[r['seed'] for r in candidate]}. Mean ± sample sd over seeds; allowed: "
        "2 sqrt(sd_r²/n_r + sd_c²/n_c).",
        "",
        "## Headline values",
        "",
        head,
        rule,
    ]
    lines += [_line(by_key[k], label) for k, label in HEADLINE if k in by_key]
    lines += ["", "## Every quality value, per split", ""]
    lines += [
        "| split | values | within 2 SE | outside | within one seed's sd (the larger side's) |",
        "|---|---|---|---|---|",
    ]
    for split in sorted({r["split"] for r in rows}):
        these = [r for r in rows if r["split"] == split]
        inside = sum(r["within"] for r in these)
        one_sd = sum(r["within_one_sd"] for r in these)
        lines.append(f"| {split} | {len(these)} | {inside} | {len(these) - inside} | {one_sd} |")
    outside = [r for r in rows if not r["within"]]
    lines += ["", f"## Outside the spread ({len(outside)})", ""]
    if outside:
        lines += [head, rule, *(_line(r) for r in outside)]
    else:
        lines.append("None.")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m experiments.compare_runs", description=__doc__.splitlines()[0]
    )
    ap.add_argument("--reference", type=Path, nargs="+", required=True, metavar="RUNS_JSON")
    ap.add_argument("--candidate", type=Path, nargs="+", required=True, metavar="RUNS_JSON")
    ap.add_argument("--out", type=Path, help="write compare.md and compare.json here")
    args = ap.parse_args(argv)
    none = dict.fromkeys(RUN_SETTINGS)
    try:
        reference, ref_settings = runs_from_files(args.reference, none)
        candidate, cand_settings = runs_from_files(args.candidate, none)
    except ValueError as e:
        ap.error(str(e))
    if ref_settings != cand_settings:
        ap.error(f"the two sides differ in their settings: {ref_settings} vs {cand_settings}")
    rows = compare(reference, candidate)
    if not rows:
        ap.error("the two sides record no quality value in common")
    command = "python -m experiments.compare_runs " + " ".join(
        ["--reference", *map(str, args.reference), "--candidate", *map(str, args.candidate)]
    )
    md = markdown(rows, reference, candidate, command)
    if args.out is None:
        print(md, end="")
        return 0
    args.out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.out / "compare.md", md)
    atomic_write_text(args.out / "compare.json", json.dumps({"rows": rows}, indent=1) + "\n")
    print(md, end="")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
