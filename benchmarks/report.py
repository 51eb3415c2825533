"""Targets and the Markdown report of a benchmark run (pure functions of the run's JSON)."""

from __future__ import annotations

from benchmarks.measure import TARGET_MODEL, TARGET_PEOPLE, TARGET_VIEWS

T_PP_LIMIT_MS = 2.0
T_3DG_BOUND_FACTOR = 1.3
OFFLINE_PEAK_FRACTION = 0.70
PIPELINE_FACTOR = 2.0
INFER_MEMORY_SPREAD = 0.10  # infer's peak RSS at every recording length within 10 % of each other

COMBINED_KEY = "pp.propose_with_matcher combined (GAT + epipolar, the pipeline's default)"


def _row(rows, **match):
    for r in rows:
        if all(r.get(k) == v for k, v in match.items()):
            return r
    return None


def targets(run: dict) -> list[dict]:
    """The tracker issue's four targets (2 CPU cores, 5 views, 4 people, paper-size models), and
    the streaming issue's: ``infer``'s peak memory flat with the recording's length.

    Each entry: name, measured, limit, unit, status ("pass", "miss" or "n/a" when the run lacks
    what the target needs), and a detail line.
    """
    lat = run.get("latency") or {}
    peaks = run.get("peaks") or {}
    off = run.get("offline") or {}
    where = dict(views=TARGET_VIEWS, people=TARGET_PEOPLE)
    row = _row(lat.get("rows", []), model=TARGET_MODEL, **where)
    tri = {
        m: _row(lat.get("triangulation", []), method=m, **where)
        for m in ("dlt", "centroid", "opencv_centroid")
    }
    model = (lat.get("models") or {}).get(f"{TARGET_VIEWS}v-{TARGET_MODEL}")
    out = []

    def add(name, measured, limit, unit, detail, ok=None):
        if measured is None or limit is None:
            status = "n/a"
        else:
            status = "pass" if (measured <= limit if ok is None else ok) else "miss"
        out.append(
            {
                "name": name,
                "measured": measured,
                "limit": limit,
                "unit": unit,
                "status": status,
                "detail": detail,
            }
        )

    t_pp = row["t_pp"]["median"] if row else None
    add(
        "t_pp <= 2 ms",
        t_pp,
        T_PP_LIMIT_MS,
        "ms",
        "median per frame: host features + graph building + GAT + proposals",
    )

    bw = peaks.get("bandwidth_gbs")
    bound = model["mlp_bytes"] / (bw * 1e9) * 1e3 if (model and bw) else None
    t_3dg = row["t_3Dg"]["median"] if row else None
    add(
        "t_3Dg <= 1.3 x weight-streaming bound",
        t_3dg,
        None if bound is None else T_3DG_BOUND_FACTOR * bound,
        "ms",
        f"bound = MLP bytes / measured bandwidth = {bound:.2f} ms"
        if bound
        else "no bound measured",
    )

    stage3 = ((off.get("models") or {}).get(TARGET_MODEL) or {}).get("stage3")
    peak = peaks.get("matmul_gflops")
    frac = stage3["gflops"] / peak if (stage3 and peak) else None
    add(
        "offline 3D >= 70% of matmul peak",
        frac,
        OFFLINE_PEAK_FRACTION,
        "fraction",
        f"{stage3['gflops']:.0f} of {peak:.0f} GFLOP/s" if frac is not None else "not measured",
        ok=None if frac is None else frac >= OFFLINE_PEAK_FRACTION,
    )

    ratio, detail = None, "not measured"
    if row and tri["centroid"]:
        t_tri = {m: r["t_tri"]["median"] for m, r in tri.items() if r}
        ratio = (row["t_pp"]["median"] + row["t_3Dg"]["median"]) / (
            row["t_pp"]["median"] + t_tri["centroid"]
        )
        others = ", ".join(
            f"{m} {(t_pp + t_3dg) / (t_pp + t):.1f}x" for m, t in t_tri.items() if m != "centroid"
        )
        detail = (
            f"(t_pp + t_3Dg) / (t_pp + t_tri), t_tri = the library's triangulate_grouped (pairwise "
            f"centroid, {t_tri['centroid']:.2f} ms); against the other rows: {others}"
        )
    add("t_pp + t_3Dg <= 2 x triangulation pipeline", ratio, PIPELINE_FACTOR, "x", detail)

    rows = (run.get("infer_memory") or {}).get("rows") or []
    peaks_mb = [r["infer"]["maxrss_mb"] for r in rows]
    spread = max(peaks_mb) / min(peaks_mb) - 1 if len(peaks_mb) > 1 else None
    add(
        "infer peak RSS within 10% across lengths",
        spread,
        INFER_MEMORY_SPREAD,
        "fraction",
        "largest / smallest peak - 1 over "
        + ", ".join(f"{r['frames']:,} frames {r['infer']['maxrss_mb']:,.0f} MB" for r in rows)
        if spread is not None
        else "fewer than two lengths measured",
    )
    return out


# --------------------------------------------------------------------------- Markdown


def _ms(s: dict | None) -> str:
    if not s:
        return "-"
    return f"{s['median']:.2f} [{s['p10']:.2f}-{s['p90']:.2f}]"


def _num(x, fmt=",.0f") -> str:
    return "-" if x is None else format(x, fmt)


def markdown(run: dict) -> str:
    m = run["machine"]
    lines = [
        f"# Benchmark run ({run['tier']})",
        "",
        f"- CPU: {m['cpu_model']}, {m['cpu_count']} cores ({m['cores_usable']} usable); "
        f"load average {m['load_before']} before, {m['load_after']} after",
        f"- JAX {m['jax']} (jaxlib {m['jaxlib']}), flax {m['flax']}, numpy {m['numpy']}, OpenCV {m['opencv']}, "
        f"Python {m['python']}; device: {m['device']}" + (" (GPU run)" if m.get("gpu") else ""),
        f"- git {run['git']['commit'][:12]}{' (uncommitted changes)' if run['git']['dirty'] else ''}; "
        f"BLAS/OpenMP threads {m['blas_threads']}; {run['date']}; total {run['seconds']:.0f} s",
    ]
    if m.get("loaded"):
        lines.append(
            "- **The machine was loaded during this run (load average above half the cores before it, or "
            "above 1.25x the cores after it, which the run alone does not reach): "
            "timings are noisy upper bounds.**"
        )
    lines += [
        "",
        "## Targets (5 views, 4 people, paper-size models)",
        "",
        "| target | measured | limit | status | how |",
        "|---|---|---|---|---|",
    ]
    for t in run.get("targets", []):
        fmt = ".2f" if t["unit"] in ("ms", "x", "fraction") else ",.0f"
        lines.append(
            f"| {t['name']} | {_num(t['measured'], fmt)} {t['unit']} | {_num(t['limit'], fmt)} | "
            f"**{t['status']}** | {t['detail']} |"
        )

    lat = run.get("latency")
    if lat:
        lines += [
            "",
            "## Per-frame latency (ms: median [p10-p90], one frame at a time, after compilation)",
            "",
            "| views | people | model | t_pp | t_3Dg | t_3Di | t_pp + t_3Dg | frames |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for r in lat["rows"]:
            lines.append(
                f"| {r['views']} | {r['people']} | {r['model']} | {_ms(r['t_pp'])} | {_ms(r['t_3Dg'])} | "
                f"{_ms(r['t_3Di'])} | {_ms(r['t_total'])} | {r['frames']} |"
            )
        lines += [
            "",
            "Triangulation of the same (true) proposals, per frame (ms):",
            "",
            "| views | people | DLT (ours) | pairwise centroid (ours) | pairwise centroid (OpenCV, "
            "the paper's code) | OpenCV vs ours, median / p99 mm |",
            "|---|---|---|---|---|---|",
        ]
        keys = sorted({(r["views"], r["people"]) for r in lat["triangulation"]})
        for v, n in keys:
            get = {
                r["method"]: r for r in lat["triangulation"] if (r["views"], r["people"]) == (v, n)
            }
            agree = get.get("opencv_centroid", {}).get("agreement_with_jax_centroid_mm")
            a = f"{agree['median']:.2f} / {agree['p99']:.2f}" if agree else "-"
            lines.append(
                f"| {v} | {n} | {_ms(get.get('dlt', {}).get('t_tri'))} | "
                f"{_ms(get.get('centroid', {}).get('t_tri'))} | "
                f"{_ms(get.get('opencv_centroid', {}).get('t_tri'))} | {a} |"
            )

    off, peaks = run.get("offline"), run.get("peaks") or {}
    if off:
        lines += [
            "",
            f"## Offline throughput ({off['frames']} frames, {off['views']} views, {off['people']} people, "
            f"{off['chunk_frames']} frames per estimator call)",
            "",
            "| model | stage 2 frames/s | stage 3 frames/s | stage 3 people/s | stage 3 GFLOP/s | "
            "% of matmul peak | MLP alone GFLOP/s (rows) | single person ms (MLP alone) | "
            "weight-streaming bound ms |",
            "|---|---|---|---|---|---|---|---|---|",
        ]
        peak, bw = peaks.get("matmul_gflops"), peaks.get("bandwidth_gbs")
        for size, e in off["models"].items():
            s3, mo, sp = e["stage3"], e["mlp_only"], e["single_person"]
            pct = f"{100 * s3['gflops'] / peak:.0f}%" if peak else "-"
            bound = f"{e['mlp_bytes'] / (bw * 1e9) * 1e3:.2f}" if bw else "-"
            lines.append(
                f"| {size} | {e['stage2']['frames_per_s']:,.0f} | {s3['frames_per_s']:,.0f} | "
                f"{s3['people_per_s']:,.0f} | {s3['gflops']:.0f} | {pct} | {mo['gflops']:.0f} ({mo['rows']}) | "
                f"{sp['predict_people_ms']['median']:.2f} ({sp['mlp_one_row_ms']['median']:.2f}) | {bound} |"
            )
        tri = next(
            (e["triangulation_dlt"] for e in off["models"].values() if "triangulation_dlt" in e),
            None,
        )
        if tri:
            lines.append(
                f"\nTriangulation (DLT) of the same recording: {tri['frames_per_s']:,.0f} frames/s."
            )

    tr = run.get("training")
    if tr:
        lines += [
            "",
            "## Training throughput (panoptic5, single-person data)",
            "",
            "| model | estimator step ms | seed samples/s | forward-backward samples/s | compile s | "
            "matcher step ms (15 graphs) | graphs/s | host batch building graphs/s | compile s per budget "
            "(budgets) |",
            "|---|---|---|---|---|---|---|---|---|",
        ]
        for size in tr["estimator"]:
            e, g = tr["estimator"][size], tr["matcher"][size]
            lines.append(
                f"| {size} | {_ms(e['step_ms'])} | {e['seed_samples_per_s']:,.0f} | "
                f"{e['forward_backward_samples_per_s']:,.0f} | {e['compile_seconds']:.1f} | {_ms(g['step_ms'])} | "
                f"{g['graphs_per_s']:,.0f} | {g['host_graphs_per_s']:,.0f} | {g['compile_seconds']:.1f} "
                f"({g['budgets_compiled']}) |"
            )

    if peaks:
        lines += [
            "",
            "## Machine peaks (measured in this run)",
            "",
            f"- float32 matmul: {peaks['matmul_gflops']:,.0f} GFLOP/s (best over sizes "
            f"{', '.join(peaks['matmul_gflops_by_size'])})",
            f"- memory read bandwidth: {peaks['bandwidth_gbs']:.1f} GB/s on a {peaks['bandwidth_array_mb']} MB "
            "array; by size: "
            + "; ".join(
                f"{k} MB: sum {v['sum']:.1f}, GEMV (n,n)@(n,1) {v['gemv_out_in']:.1f}, "
                f"(1,n)@(n,n) {v['gemv_in_out']:.1f} GB/s"
                for k, v in peaks["bandwidth_by_size"].items()
            ),
        ]
        if "spread" in peaks:
            mm, bw = peaks["matmul_gflops_start_end"], peaks["bandwidth_gbs_start_end"]
            lines.append(
                f"- measured at the start and again at the end of the run: matmul {mm[0]:,.0f} / {mm[1]:,.0f} "
                f"GFLOP/s, bandwidth {bw[0]:.1f} / {bw[1]:.1f} GB/s (the better counts; spread "
                f"{100 * peaks['spread']:.0f}%{', the load changed during the run' if peaks['spread'] > 0.15 else ''})"
            )

    mem = run.get("memory")
    trk = run.get("tracking")
    if trk:
        lines += [
            "",
            f"## Tracking and streaming filter (target <= {trk['limit_ms_per_person']} ms per "
            "person per frame)",
            "",
            "Per frame: `tracking.update_tracks` (2D evidence of 5 cameras) + "
            "`smoothing.one_euro_update`; median [p10-p90] ms.",
            "",
            "| people | tracker ms | One-Euro ms | per person ms | target |",
            "|---|---|---|---|---|",
        ]
        for r in trk["rows"]:
            lines.append(
                f"| {r['people']} | {_ms(r['tracker_ms'])} | {_ms(r['one_euro_ms'])} | "
                f"{_ms(r['per_person_ms'])} | {r['status']} |"
            )
    ad = run.get("adapt")
    if ad:
        lines += [
            "",
            f"## Adapting the estimator to a recording (target <= "
            f"{ad['limit_seconds_per_1000_frames']:.0f} s per 1,000 frames)",
            "",
            "`adapt.adapt_estimator`, quick-size MLP, 5 views, 4 people, epipolar proposals, every "
            "default step run (no early stop): the whole call, proposals and compilation included.",
            "",
            "| frames | people adapt / held out | steps | proposals s | training s | ms per step "
            "| s per 1,000 frames | CPU s per 1,000 frames | target |",
            "|---|---|---|---|---|---|---|---|---|",
            f"| {ad['frames']} | {ad['people_adapt']} / {ad['people_heldout']} | {ad['steps']} "
            f"| {ad['grouping_seconds']:.1f} | {ad['training_seconds']:.1f} "
            f"| {ad['ms_per_step_incl_compile_and_checks']:.0f} "
            f"| {ad['seconds_per_1000_frames']:.1f} "
            f"| {1000 * ad['cpu_seconds'] / ad['frames']:.1f} | {ad['status']} |",
        ]
    am = run.get("adapt_matcher")
    if am:
        lines += [
            "",
            f"## Adapting the matcher to a recording (target <= "
            f"{am['limit_seconds_per_1000_frames']:.0f} s per 1,000 frames)",
            "",
            "`adapt.adapt_matcher`, the paper's GAT (the quick scale's), 5 views, 4 people, given "
            "pair labels, every "
            "default step run (no early stop): the whole call, compilation included.",
            "",
            "| frames | frames adapt / held out | pairs | steps | s | ms per step "
            "| s per 1,000 frames | CPU s per 1,000 frames | target |",
            "|---|---|---|---|---|---|---|---|---|",
            f"| {am['frames']} | {am['frames_adapt']} / {am['frames_heldout']} "
            f"| {am['pairs_adapt']} | {am['steps']} | {am['seconds']:.1f} "
            f"| {am['ms_per_step_incl_compile_and_checks']:.0f} "
            f"| {am['seconds_per_1000_frames']:.1f} "
            f"| {1000 * am['cpu_seconds'] / am['frames']:.1f} | {am['status']} |",
        ]
    if mem:
        lines += [
            "",
            f"## Peak memory per group ({run['memory_method']})",
            "",
            "| group | peak RSS MB | RSS after imports MB | growth MB | device peak MB | seconds |",
            "|---|---|---|---|---|---|",
        ]
        for g, r in mem.items():
            dev = "-" if r.get("device_peak_mb") is None else f"{r['device_peak_mb']:,.0f}"
            lines.append(
                f"| {g} | {r['maxrss_mb']:,.0f} | {r['rss_after_import_mb']:,.0f} | "
                f"{r['maxrss_mb'] - r['rss_after_import_mb']:,.0f} | {dev} | {r['seconds']:.0f} |"
            )

    im = run.get("infer_memory")
    if im:
        lines += [
            "",
            f"## Peak memory of infer against the recording's length (chunks of "
            f"{im['chunk_frames']} frames)",
            "",
            "`mvpose-jax infer` (geometric matcher, DLT) on an npz of 4 people, 5 cameras, each length "
            "in its own process (`benchmarks.memory`); the whole-recording path (load, "
            "`run_pipeline`, `save_poses`) for comparison.",
            "",
            "| frames | npz MB | infer peak RSS MB | infer s | frames/s | whole-recording path peak RSS MB |",
            "|---|---|---|---|---|---|",
        ]
        for r in im["rows"]:
            whole = "-" if r.get("whole") is None else f"{r['whole']['maxrss_mb']:,.0f}"
            lines.append(
                f"| {r['frames']:,} | {r['file_mb']:,.1f} | {r['infer']['maxrss_mb']:,.0f} | "
                f"{r['infer']['seconds']:.0f} | {r['infer']['frames_per_s']:,.0f} | "
                f"{whole} |"
            )

    bd = (lat or {}).get("breakdown")
    if bd:
        lines += [
            "",
            f"## Breakdown ({bd['views']} views, {bd['people']} people, {bd['model']} model; ms per frame)",
            "",
            f"Graph budgets (nodes, detections, edges, graphs): {', '.join(bd['graph_budgets'])}; "
            f"estimator bucket: {bd['bucket']} rows.",
            "",
            "| component | median | p10 | p90 |",
            "|---|---|---|---|",
        ]
        for name, s in bd["parts_ms"].items():
            lines.append(f"| {name} | {s['median']:.3f} | {s['p10']:.3f} | {s['p90']:.3f} |")
        if run.get("profile"):
            lines += ["", "Where the time goes:", ""] + [f"- {p}" for p in run["profile"]]

    if run.get("pipeline"):
        from benchmarks.pipeline import markdown as pipeline_markdown

        lines += pipeline_markdown(run["pipeline"])

    if run.get("batch"):
        from benchmarks.batch import markdown as batch_markdown

        lines += batch_markdown(run["batch"])

    if run.get("errors"):
        lines += ["", "## Errors", ""] + [f"- {g}: {e}" for g, e in run["errors"].items()]
    return "\n".join(lines) + "\n"


def _patterns(run: dict, bd: dict) -> str:
    row = _row(
        (run.get("latency") or {}).get("rows", []),
        views=bd["views"],
        people=bd["people"],
        model=bd["model"],
    )
    if not row or "count_patterns" not in row:
        return ""
    return (
        f" ({row['count_patterns']} patterns in these {row['frames']} frames; the frame-by-frame numbers "
        f"are the steady state, every pattern met once in the warm-up)"
    )


def profile_notes(run: dict) -> list[str]:
    """Plain statements of where the target configuration's time goes, from the breakdown."""
    bd = (run.get("latency") or {}).get("breakdown")
    if not bd:
        return []
    p = {k: v["median"] for k, v in bd["parts_ms"].items()}
    notes = []
    pp = p.get("pp.total")
    if pp:
        call = p["pp.gat_match_table (features + GAT, one call)"]
        net = p["pp.gat_device_only"]
        notes.append(
            f"t_pp {pp:.2f} ms: the matcher's call {call:.2f} ms ({100 * call / pp:.0f}%): the network on "
            f"device-resident graphs {net:.2f} ms (first projection {p['pp.gat_first_projection']:.2f} + attention "
            f"layers {p['pp.gat_attention_layers']:.2f}) and {max(0.0, call - net):.2f} ms of features, "
            f"transfers, dispatch and match table; proposals {p['pp.propose_people (network scores)']:.2f} ms "
            f"({p['pp.propose_people (oracle scores)']:.2f} ms with oracle scores, which accept the true pairs). "
            f"A frame whose skeleton counts per view were not met before also builds its graph: "
            f"{p['pp.graph_for_new_counts (build + to device)']:.2f} ms{_patterns(run, bd)}. The default "
            f"propose_with_matcher: "
            f"{p['pp.propose_with_matcher (default 32-frame chunk)']:.2f} ms"
            + (
                f"; combined with epipolar geometry (the pipeline's default with a matcher): "
                f"{combined:.2f} ms."
                if (combined := p.get(COMBINED_KEY)) is not None
                else "."
            )
        )
        row = _row(
            (run.get("latency") or {}).get("rows", []),
            views=bd["views"],
            people=bd["people"],
            model=bd["model"],
        )
        if row and row["t_pp"]["median"] > 1.2 * pp:
            notes.append(
                f"In the frame-by-frame loop t_pp is {row['t_pp']['median']:.2f} ms against {pp:.2f} ms for the "
                f"same calls back to back (the breakdown): there the 3D stage runs between two frames' "
                f"proposals, which then start with cold caches and idle worker threads."
            )
    idle = [k for k in p if k.startswith("pp.total after")]
    if idle and pp and p.get("3d.total"):
        ms = idle[0].split("after ")[1].split(" ms")[0]
        pp_idle, g3_idle = p[idle[0]], p[f"3d.total after {ms} ms idle"]
        notes.append(
            f"After {ms} ms of idling before each call (what a 30 fps camera stream does between frames): "
            f"t_pp {pp_idle:.2f} ms and t_3Dg {g3_idle:.2f} ms, against {pp:.2f} and {p['3d.total']:.2f} ms back "
            f"to back: after a pause XLA's worker threads (and the cores under them) have gone idle, "
            f"and the parallel operations of the next call start by waking them."
        )
    g3 = p.get("3d.total")
    if g3:
        keys = [k for k in p if k.startswith("3d.mlp_device")]
        bucket = next(k for k in keys if "bucket" in k)
        people = next(k for k in keys if "people" in k)
        feat = next(k for k in p if k.startswith("3d.features_device"))
        notes.append(
            f"t_3Dg {g3:.2f} ms: MLP on the {bd['bucket']}-row bucket {p[bucket]:.2f} ms vs "
            f"{p[people]:.2f} ms on the {bd['people']} real rows and {p['3d.mlp_device (1 row)']:.2f} ms on one row; "
            f"features {p[feat]:.2f} ms; grouping {p['3d.group_people']:.2f} ms; the rest of "
            f"estimate_grouped (padding, transfers, dispatch) "
            f"{max(0.0, p['3d.estimate_grouped'] - p[bucket] - p[feat]):.2f} ms."
        )
        bw = (run.get("peaks") or {}).get("bandwidth_gbs")
        if bw:
            bound = bd["mlp_bytes"] / (bw * 1e9) * 1e3
            one = p["3d.mlp_device (1 row)"]
            per_row = (p[bucket] - one) / max(1, bd["bucket"] - 1)
            if p[bucket] > 1.3 * one:
                why = (
                    f"past one row the products are compute-bound, about {per_row:.2f} ms per added row, "
                    "so every padding row of the bucket costs time"
                )
            else:
                why = "extra rows cost little at this size"
            notes.append(
                f"The MLP's weights take {bound:.2f} ms to stream at the measured {bw:.1f} GB/s; one row runs "
                f"in {one:.2f} ms ({one / bound:.1f}x the bound), {bd['people']} rows in {p[people]:.2f} ms "
                f"({p[people] / bound:.1f}x) and the {bd['bucket']}-row bucket in {p[bucket]:.2f} ms "
                f"({p[bucket] / bound:.1f}x): {why}."
            )
    off = ((run.get("offline") or {}).get("models") or {}).get(bd["model"])
    peak = (run.get("peaks") or {}).get("matmul_gflops")
    if off and peak:
        s3 = off["stage3"]
        per_chunk = s3["seconds"] / max(1, off.get("chunks", 1))
        feat = off.get("features_only", {}).get("seconds")
        notes.append(
            f"Offline 3D: {s3['gflops']:.0f} GFLOP/s over the whole stage ({100 * s3['gflops'] / peak:.0f}% of the "
            f"{peak:.0f} GFLOP/s peak); the MLP alone on a {off['mlp_only']['rows']}-row chunk reaches "
            f"{off['mlp_only']['gflops']:.0f} GFLOP/s. Per chunk: {1e3 * per_chunk:.1f} ms in all, MLP "
            f"{1e3 * off['mlp_only']['seconds']:.1f} ms"
            + (f", features {1e3 * feat:.1f} ms" if feat else "")
            + f", the rest (grouping, padding, transfers) "
            f"{1e3 * max(0.0, per_chunk - off['mlp_only']['seconds'] - (feat or 0.0)):.1f} ms."
        )
    return notes
