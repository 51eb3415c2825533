"""The benchmark groups: each is a function ``tier -> JSON-able dict`` run in its own process.

* `peaks`: the machine's float32 matmul peak and memory read bandwidth, measured with jitted JAX.
* `latency`: per-frame t_pp, t_3Dg, t_3Di and the triangulation rows, over views x people x model
  size, and the time breakdown of the target configuration.
* `offline`: a long recording in batches: frames/s and people/s of both stages, GFLOP/s of the 3D
  stage, single-person latency.
* `training`: samples/s and compile time of the estimator's and the matcher's train steps.
* `tracking`: the streaming path's host work per frame (tracker update and One-Euro filter) per
  person, at 1, 4, 8 and 16 people.
* `pipeline`: what users run (`infer`'s default with models, the paper's method, the geometric
  default, epipolar + DLT), live and offline, with the time per stage (`benchmarks.pipeline`).
* `adapt`: `adapt.adapt_estimator` (quick-size MLP, 5 views, 4 people, epipolar proposals, every
  step run) in seconds per 1,000 frames, against the issue's bound.

Every timed call is warmed up first (every shape it meets is compiled before timing), and every
clock stops after the result is on the host or after `jax.block_until_ready`.
"""

from __future__ import annotations

import dataclasses
import gc
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from benchmarks import memory, scenes
from mvpose_jax.adapt import (
    SECONDS_PER_1000_FRAMES,
    AdaptConfig,
    MatcherAdaptConfig,
    adapt_estimator,
    adapt_matcher,
)
from mvpose_jax.cameras import Rig, rig_centre_and_radius
from mvpose_jax.data.calibration import load_rig
from mvpose_jax.estimator_training import estimator_training
from mvpose_jax.features import assemble_features, estimator_inputs, single_person_samples
from mvpose_jax.graphs import (
    build_graphs,
    detection_features,
    graph_budget,
    make_pool,
    match_table,
    next_power_of_two,
    sample_batches,
)
from mvpose_jax.lifting import (
    estimate_grouped,
    group_people,
    members_from_identity,
    poses_of_members,
    predict_people,
    triangulate_grouped,
)
from mvpose_jax.matcher_training import matcher_loss_fn
from mvpose_jax.matching import gat_match_table, propose_with_matcher
from mvpose_jax.models import MatchingGAT, to_world
from mvpose_jax.proposals import propose_people
from mvpose_jax.skeletons import Detections
from mvpose_jax.synthetic import generate_single_person_recordings
from mvpose_jax.train import init_train_state, make_optimizer, make_train_step
from mvpose_jax.trained import EstimatorConfig, MatcherConfig

# The configuration the targets are stated for (DESIGN.md §5 and the tracker issue).
TARGET_VIEWS, TARGET_PEOPLE, TARGET_MODEL = 5, 4, "paper"


@dataclasses.dataclass(frozen=True)
class Tier:
    """How much each group measures.

    Attributes:
      name: "full", "quick" or "smoke".
      views, people: the per-frame latency grid.
      frames: frames per latency configuration (each timed once, after a warm-up pass).
      models: model sizes of the latency grid ("paper", "quick").
      quick_model_configs: (views, people) where the quick-size model is timed too, when
        "quick" is not in ``models`` for the whole grid (None: the whole grid).
      peak_sizes: square matmul sizes tried for the float32 peak.
      peak_repeats: repeats per peak measurement (the best counts).
      bandwidth_mb: array sizes (MB) of the bandwidth measurement; the first is compared with
        the model (112: the paper MLP's weight bytes at 5 views, so the same cache regime as its
        forward pass), the others are context (past the last-level cache).
      offline_frames: length of the offline recording (5 views, 4 people).
      offline_chunk: frames per estimator call offline (people per call = chunk x people).
      offline_repeats: timed passes over the offline recording.
      single_repeats: repeats of the single-person latency.
      train_batch: estimator seed samples per step (graphs per step: the matcher's own 15).
      train_steps: timed train steps per model.
      model_sizes: model sizes of the offline and training groups.
      matcher_batches: distinct composed batches the matcher's step is timed on (each new graph
        budget among them is compiled during the warm-up).
      memory_frames: recording lengths of the ``infer_memory`` group (`benchmarks.memory`).
      memory_chunk: ``infer --chunk-frames`` there.
      memory_whole_max: lengths up to this also run the whole-recording path, for comparison.
      adapt_frames: length of the ``adapt`` group's recording (5 views, 4 people).
      adapt_steps: its fine-tuning steps (the default `AdaptConfig.max_steps` but in smoke).
      adapt_matcher_steps: the ``adapt_matcher`` group's steps on the same recording (the
        default `MatcherAdaptConfig.max_steps` but in smoke).
    """

    name: str
    views: tuple[int, ...]
    people: tuple[int, ...]
    frames: int
    models: tuple[str, ...]
    quick_model_configs: tuple[tuple[int, int], ...] | None
    peak_sizes: tuple[int, ...]
    peak_repeats: int
    bandwidth_mb: tuple[int, ...]
    offline_frames: int
    offline_chunk: int
    offline_repeats: int
    single_repeats: int
    train_batch: int
    train_steps: int
    model_sizes: tuple[str, ...]
    matcher_batches: int
    memory_frames: tuple[int, ...]
    memory_chunk: int
    memory_whole_max: int
    adapt_frames: int = 1000
    adapt_steps: int = AdaptConfig.max_steps
    adapt_matcher_steps: int = MatcherAdaptConfig.max_steps


TIERS = {
    "full": Tier(
        "full",
        views=(2, 3, 5, 8),
        people=(1, 2, 4, 8, 16),
        frames=200,
        models=("paper", "quick"),
        quick_model_configs=None,
        peak_sizes=(1024, 2048, 4096),
        peak_repeats=7,
        bandwidth_mb=(112, 2048),
        offline_frames=2048,
        offline_chunk=256,
        offline_repeats=3,
        single_repeats=200,
        train_batch=256,
        train_steps=10,
        model_sizes=("paper", "quick"),
        matcher_batches=20,
        memory_frames=(1_000, 10_000, 100_000),
        memory_chunk=256,
        memory_whole_max=10_000,
    ),
    "quick": Tier(
        "quick",
        views=(2, 5, 8),
        people=(1, 4, 16),
        frames=32,
        models=("paper",),
        quick_model_configs=((5, 4),),
        peak_sizes=(2048,),
        peak_repeats=5,
        bandwidth_mb=(112, 1024),
        offline_frames=256,
        offline_chunk=128,
        offline_repeats=2,
        single_repeats=50,
        train_batch=256,
        train_steps=3,
        model_sizes=("paper", "quick"),
        matcher_batches=4,
        memory_frames=(1_000, 10_000),
        memory_chunk=256,
        memory_whole_max=10_000,
    ),
    "smoke": Tier(
        "smoke",
        views=(5,),
        people=(2,),
        frames=4,
        models=("quick",),
        quick_model_configs=None,
        peak_sizes=(512,),
        peak_repeats=3,
        bandwidth_mb=(32,),
        offline_frames=16,
        offline_chunk=8,
        offline_repeats=1,
        single_repeats=5,
        train_batch=16,
        train_steps=2,
        model_sizes=("quick",),
        matcher_batches=1,
        memory_frames=(24, 48),
        memory_chunk=8,
        memory_whole_max=24,
        adapt_frames=50,  # the fewest with a held-out block (frames 40-49) at the defaults
        adapt_steps=2,
        adapt_matcher_steps=2,
    ),
}


# --------------------------------------------------------------------------- timing helpers


def summary(seconds, scale: float = 1e3) -> dict:
    """Median, p10, p90 and quartiles of a sample of durations (milliseconds by default)."""
    s = np.asarray(seconds, np.float64) * scale
    p10, q1, med, q3, p90 = np.percentile(s, [10, 25, 50, 75, 90])
    return {
        "median": float(med),
        "p10": float(p10),
        "p90": float(p90),
        "iqr": [float(q1), float(q3)],
        "mean": float(s.mean()),
        "n": int(s.size),
    }


def timed(fn: Callable, *args) -> tuple[float, object]:
    """(seconds, result) of one call; the clock stops when the result is ready."""
    t = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    return time.perf_counter() - t, out


def repeat(fn: Callable, *args, n: int, warmup: int = 1) -> np.ndarray:
    """Durations of ``n`` calls after ``warmup`` untimed ones."""
    for _ in range(warmup):
        jax.block_until_ready(fn(*args))
    gc.collect()
    return np.array([timed(fn, *args)[0] for _ in range(n)])


def param_bytes(params) -> int:
    return int(sum(x.size * x.dtype.itemsize for x in jax.tree_util.tree_leaves(params)))


def mlp_flops(params) -> int:
    """Multiply-add FLOPs (2 per MAC) of one person's forward pass: every kernel's in x out."""
    return int(sum(2 * x.size for x in jax.tree_util.tree_leaves(params) if x.ndim == 2))


# --------------------------------------------------------------------------- peaks


def peaks(tier: Tier) -> dict:
    """float32 matmul GFLOP/s (best of ``peak_repeats``) and memory read GB/s (jitted sum and GEMV)."""
    key = jax.random.key(0)
    matmul = {}
    for n in tier.peak_sizes:
        a = jax.random.normal(key, (n, n), jnp.float32)
        b = jax.random.normal(jax.random.fold_in(key, 1), (n, n), jnp.float32)
        t = repeat(jax.jit(jnp.dot), a, b, n=tier.peak_repeats).min()
        matmul[str(n)] = 2.0 * n**3 / t / 1e9
        del a, b
    bandwidth = {}
    for mb in tier.bandwidth_mb:
        n = int(np.sqrt(mb * 2**20 / 4))
        w = jnp.full(
            (n, n), 0.5, jnp.float32
        )  # values do not matter to a read; random ones are slow to draw
        row, col = jnp.ones((1, n), jnp.float32), jnp.ones((n, 1), jnp.float32)
        nbytes = w.size * 4
        t_sum = repeat(jax.jit(jnp.sum), w, n=tier.peak_repeats).min()
        # Both GEMV layouts: (n, n) @ (n, 1) is the estimator's (kernels stored (out, in)).
        t_out_in = repeat(jax.jit(jnp.dot), w, col, n=tier.peak_repeats).min()
        t_in_out = repeat(jax.jit(jnp.dot), row, w, n=tier.peak_repeats).min()
        bandwidth[str(mb)] = {
            "sum": nbytes / t_sum / 1e9,
            "gemv_out_in": nbytes / t_out_in / 1e9,
            "gemv_in_out": nbytes / t_in_out / 1e9,
            "bytes": int(nbytes),
        }
        del w
    first = bandwidth[str(tier.bandwidth_mb[0])]
    return {
        "matmul_gflops": max(matmul.values()),
        "matmul_gflops_by_size": matmul,
        "bandwidth_gbs": max(first["sum"], first["gemv_out_in"], first["gemv_in_out"]),
        "bandwidth_array_mb": tier.bandwidth_mb[0],
        "bandwidth_by_size": bandwidth,
        "how": "matmul: jitted jnp.dot of two random n x n float32 matrices, best of the repeats, "
        "2n^3 FLOP; bandwidth: bytes of an n x n float32 array / best time of a jitted jnp.sum "
        "of it, of an (n, n) @ (n, 1) GEMV (the MLP's single-person access pattern) and of a "
        "(1, n) @ (n, n) one, best of the three at the first size (the paper MLP's weight "
        "bytes, so in the same cache regime as its forward pass); other sizes for context.",
    }


# --------------------------------------------------------------------------- per-frame latency


def _frame(det: Detections, f: int) -> Detections:
    return Detections(det.xy[f : f + 1], det.score[f : f + 1], det.count[f : f + 1])


def _numpy_detections(rec) -> tuple[Detections, np.ndarray]:
    """The recording's detections as numpy, and its true proposals: members (F, G, C)."""
    d = rec.detections
    det = Detections(
        np.asarray(d.xy, np.float32), np.asarray(d.score, np.float32), np.asarray(d.count)
    )
    G = np.shape(rec.ground_truth.valid)[1]
    return det, members_from_identity(np.asarray(rec.identity), G)


def _pipeline_fns(rig: Rig, det: Detections, members: np.ndarray, matcher, estimator):
    """The per-frame calls, each f -> something ready on the host.

    t_pp: match scores of one frame (one graph, no chunk padding) and its proposals; t_3Dg: the
    pipeline's 3D stage (`inference.poses_of_members`: grouping, features, MLP) on the frame's
    people, grouped by their true identities.
    """
    P = det.score.shape[2]

    def t_pp(f):
        d = _frame(det, f)
        rows, scores = gat_match_table(matcher, d, frames_per_call=1)
        return propose_people(rows, scores, d.count, num_skeletons=P)

    def t_3dg(f):
        poses, _ = poses_of_members(rig, _frame(det, f), members[f : f + 1], estimator=estimator)
        return int(poses.valid.sum())

    return t_pp, t_3dg


def _tri_fns(rig: Rig, det: Detections, members: np.ndarray):
    cams = scenes.opencv_cameras(rig)
    min_views = min(2, rig.num_cameras)

    def tri(method):
        def fn(f):
            return poses_of_members(rig, _frame(det, f), members[f : f + 1], method=method)[
                0
            ].valid.sum()

        return fn

    def opencv(f):
        xy, score = group_people(det.xy[f : f + 1], det.score[f : f + 1], members[f : f + 1])
        present = (score > 0).any(-1).sum(-1) >= min_views  # (1, G): the pipeline's presence rule
        return scenes.opencv_pairwise_centroid(cams, xy[present], score[present])

    return {"dlt": tri("dlt"), "centroid": tri("centroid"), "opencv_centroid": opencv}


def latency(tier: Tier) -> dict:
    """Per-frame latency of both pipelines over the tier's grid, and the target's breakdown."""
    K = 18
    rows, tri_rows, compile_s = [], [], {}
    breakdown = None
    models: dict[tuple[int, str], tuple] = {}
    # The breakdown is taken on the target configuration, or on the first one when the tier lacks it.
    target = (TARGET_VIEWS, TARGET_PEOPLE, TARGET_MODEL)
    if (
        TARGET_VIEWS not in tier.views
        or TARGET_PEOPLE not in tier.people
        or TARGET_MODEL not in tier.models
    ):
        target = (tier.views[0], tier.people[0], tier.models[0])
    for V in tier.views:
        for n in tier.people:
            rig, rec = scenes.recording(V, n, tier.frames, seed=V * 100 + n)
            det, members = _numpy_detections(rec)
            frames = range(tier.frames)
            sizes = [
                s
                for s in scenes.MODEL_SIZES
                if s in tier.models
                or (
                    s == "quick" and tier.quick_model_configs and (V, n) in tier.quick_model_configs
                )
            ]
            for size in sizes:
                if (V, size) not in models:
                    mlp, gat = scenes.MODEL_SIZES[size]
                    models[(V, size)] = (
                        scenes.matcher_for(rig, K, gat),
                        scenes.estimator_for(rig, K, mlp),
                    )
                matcher, estimator = models[(V, size)]
                t_pp, t_3dg = _pipeline_fns(rig, det, members, matcher, estimator)
                # Warm-up: one pass over every frame compiles every graph budget the frames meet
                # (the people bucket and the other shapes are fixed by the recording) and caches
                # every skeleton-count pattern's graph, so the timed pass is the steady state of a
                # long stream; what a pattern met for the first time adds is in the breakdown
                # (pp.graph_for_new_counts), and how many frames bring one is in the row.
                start = time.perf_counter()
                for f in frames:
                    t_pp(f), t_3dg(f)
                compile_s[f"{V}v{n}p-{size}"] = time.perf_counter() - start
                gc.collect()
                pp, g3, people = [], [], []
                for f in frames:  # frame by frame, as a live system runs: proposals, then 3D
                    t1, _ = timed(t_pp, f)
                    t2, num = timed(t_3dg, f)
                    pp.append(t1)
                    g3.append(t2)
                    people.append(num)
                people = np.asarray(people)
                rows.append(
                    {
                        "views": V,
                        "people": n,
                        "model": size,
                        "frames": len(pp),
                        "mean_people_estimated": float(people.mean()),
                        "t_pp": summary(pp),
                        "t_3Dg": summary(g3),
                        "t_3Di": summary(np.asarray(g3) / np.maximum(people, 1)),
                        "t_total": summary(np.asarray(pp) + np.asarray(g3)),
                        "graph_budget_nodes": sorted({_budget(det, f).nodes for f in frames}),
                        "count_patterns": len({det.count[f].tobytes() for f in frames}),
                        "people_bucket": next_power_of_two(n),
                    }
                )
                if (V, n, size) == target:
                    breakdown = _breakdown(
                        rig, det, members, n, matcher, estimator, size, frames, t_pp, t_3dg
                    )
            # Triangulation rows: model-independent, on the same (true) proposals.
            for method, fn in _tri_fns(rig, det, members).items():
                for f in frames[:3]:  # one shape per recording: a few calls warm it up
                    fn(f)
                times = [timed(fn, f)[0] for f in frames]
                row = {
                    "views": V,
                    "people": n,
                    "method": method,
                    "frames": len(times),
                    "t_tri": summary(times),
                }
                if method == "opencv_centroid":
                    row["agreement_with_jax_centroid_mm"] = _agreement(rig, det, members, frames)
                tri_rows.append(row)
    sizes = {}
    for (V, size), (matcher, estimator) in models.items():
        sizes[f"{V}v-{size}"] = {
            "mlp_params": int(sum(x.size for x in jax.tree_util.tree_leaves(estimator.params))),
            "mlp_bytes": param_bytes(estimator.params),
            "mlp_flops_per_person": mlp_flops(estimator.params),
            "gat_params": int(sum(x.size for x in jax.tree_util.tree_leaves(matcher.params))),
            "mlp_widths": list(estimator.config.mlp.widths),
            "gat_widths": list(matcher.config.gat.widths),
        }
    return {
        "rows": rows,
        "triangulation": tri_rows,
        "warmup_seconds": compile_s,
        "models": sizes,
        "breakdown": breakdown,
    }


def _warmup_frames(det: Detections, frames) -> list[int]:
    """The first two frames and the first frame of every other graph budget."""
    first: dict = {}
    for f in frames:
        first.setdefault(_budget(det, f), f)
    return sorted(set(list(frames)[:2]) | set(first.values()))


def _identity(members: np.ndarray, num_skeletons: int) -> np.ndarray:
    """(F, G, C) members -> (F, C, P) person of each skeleton, -1 none."""
    F, G, C = members.shape
    identity = np.full((F, C, num_skeletons), -1, np.int64)
    f, g, c = np.nonzero(members >= 0)
    identity[f, c, members[f, g, c]] = g
    return identity


def _budget(det: Detections, f: int):
    count = det.count[f]
    n_det = int(count.sum())
    n_match = (n_det**2 - int((count**2).sum())) // 2
    return graph_budget(n_det, n_match, 1)


def _agreement(rig: Rig, det: Detections, members: np.ndarray, frames) -> dict:
    """How far our JAX pairwise centroid lies from the OpenCV reference (both valid), in mm."""
    cams = scenes.opencv_cameras(rig)
    diffs = []
    for f in list(frames)[:20]:
        xy, score = group_people(det.xy[f : f + 1], det.score[f : f + 1], members[f : f + 1])
        ours = triangulate_grouped(rig, xy, score, "centroid")[0]
        ref, ok = scenes.opencv_pairwise_centroid(cams, xy[0], score[0])
        both = ok & ours.keypoint_valid[0]
        diffs.append(np.linalg.norm(ref[both] - ours.xyz[0][both], axis=-1) * 1e3)
    d = np.concatenate(diffs) if diffs else np.zeros(1)
    return {
        "median": float(np.median(d)),
        "p99": float(np.percentile(d, 99)),
        "keypoints": int(d.size),
    }


# A camera stream leaves the pipeline idle between frames (25+ ms at 30 fps, more than the
# pipeline's own time): the breakdown times each stage after such a pause too.
IDLE_MS = 5
IDLE_SECONDS = IDLE_MS / 1000


def _breakdown(rig, det, members, n, matcher, estimator, size, frames, t_pp, t_3dg) -> dict:
    """Where the time of one frame goes, component by component (medians over the frames, ms)."""
    P = det.score.shape[2]
    frames = list(frames)
    parts: dict[str, dict] = {}

    warm = _warmup_frames(det, frames)

    def measure(name, fn, before=None):
        for f in warm:
            fn(f)
        times = []
        for f in frames:
            if before is not None:
                before()  # untimed
            times.append(timed(fn, f)[0])
        parts[name] = summary(times)

    def idle():
        time.sleep(IDLE_SECONDS)

    # ---- t_pp: the matcher's call (features and network in one jit, graphs cached per count
    # pattern), then proposals; inside it, the network on device-resident inputs, and the graph
    # building a frame with a new count pattern pays.
    feats = {f: detection_features(rig, *_frame(det, f)[:2]) for f in frames}
    valid = {f: np.arange(P)[None, None] < _frame(det, f).count[..., None] for f in frames}
    batches = {f: build_graphs(feats[f], valid[f], num_graphs=1) for f in frames}
    tables = {f: gat_match_table(matcher, _frame(det, f), frames_per_call=1) for f in frames}
    identity = _identity(members, det.score.shape[2])
    oracle = {}
    for f in frames:
        labelled = build_graphs(feats[f], valid[f], identity[f : f + 1], num_graphs=1)
        oracle[f] = match_table(labelled, labelled.label)
    on_device = {f: jax.device_put(batches[f]) for f in frames}
    model_fn = jax.jit(lambda params, b: nnx.merge(matcher.graphdef, params, matcher.rest)(b))
    first_fn = jax.jit(
        lambda params, b: nnx.merge(matcher.graphdef, params, matcher.rest).first_projection(b)
    )

    def attention_only(params, b, z):
        model = nnx.merge(matcher.graphdef, params, matcher.rest)
        h = model.layers[0].attend(z, b.graphs)
        for layer in model.layers[1:]:
            h = layer(jax.nn.leaky_relu(h, model.between_slope), b.graphs)
        return h

    attention_fn = jax.jit(attention_only)
    z_first = {f: first_fn(matcher.params, on_device[f]) for f in frames}
    no_features = {f: np.zeros(np.shape(valid[f]) + (0,), np.float32) for f in frames}
    measure(
        "pp.gat_match_table (features + GAT, one call)",
        lambda f: gat_match_table(matcher, _frame(det, f), frames_per_call=1),
    )
    measure(
        "pp.graph_for_new_counts (build + to device)",
        lambda f: jax.device_put(build_graphs(no_features[f], valid[f], num_graphs=1)),
    )
    measure("pp.gat_device_only", lambda f: model_fn(matcher.params, on_device[f]))
    measure("pp.gat_first_projection", lambda f: first_fn(matcher.params, on_device[f]))
    measure(
        "pp.gat_attention_layers", lambda f: attention_fn(matcher.params, on_device[f], z_first[f])
    )
    measure(
        "pp.propose_people (network scores)",
        lambda f: propose_people(*tables[f], _frame(det, f).count, num_skeletons=P),
    )
    measure(
        "pp.propose_people (oracle scores)",
        lambda f: propose_people(*oracle[f], _frame(det, f).count, num_skeletons=P),
    )
    measure("pp.total", t_pp)
    measure(f"pp.total after {IDLE_MS} ms idle", t_pp, before=idle)
    measure(
        "pp.propose_with_matcher (default 32-frame chunk)",
        lambda f: propose_with_matcher(matcher, _frame(det, f)),
    )
    measure(
        "pp.propose_with_matcher combined (GAT + epipolar, the pipeline's default)",
        lambda f: propose_with_matcher(matcher, _frame(det, f), mode="combined"),
    )

    # ---- t_3Dg: grouping, estimate_grouped, then its insides: features and MLP (poses_of_members
    # is group_people + estimate_grouped)
    centre, radius = rig_centre_and_radius(estimator.rig_infer)
    graphdef, rest = estimator.graphdef, estimator.rest
    feature_fn = jax.jit(
        lambda r, xy, s: assemble_features(estimator_inputs(r, xy, s), (s > 0).any(axis=-1))
    )
    mlp_fn = jax.jit(
        lambda params, x: to_world(nnx.merge(graphdef, params, rest)(x), centre, radius)
    )
    grouped = {
        f: group_people(det.xy[f : f + 1], det.score[f : f + 1], members[f : f + 1]) for f in frames
    }
    bucket = next_power_of_two(n)

    def padded(f, rows_):
        xy, sc = grouped[f][0][0], grouped[f][1][0]  # (G, C, K, 2), (G, C, K)
        pad = [(0, rows_ - len(xy))] + [(0, 0)] * 3
        return jnp.asarray(np.pad(xy, pad)), jnp.asarray(np.pad(sc, pad[:-1]))

    dev_bucket = {f: padded(f, bucket) for f in frames}
    dev_exact = {f: padded(f, n) for f in frames}
    feats_bucket = {f: feature_fn(estimator.rig_infer, *dev_bucket[f]) for f in frames}
    feats_exact = {f: feature_fn(estimator.rig_infer, *dev_exact[f]) for f in frames}
    measure(
        "3d.group_people",
        lambda f: group_people(det.xy[f : f + 1], det.score[f : f + 1], members[f : f + 1]),
    )
    measure("3d.estimate_grouped", lambda f: estimate_grouped(estimator, *grouped[f]))
    measure(
        f"3d.features_device ({bucket} rows)",
        lambda f: feature_fn(estimator.rig_infer, *dev_bucket[f]),
    )
    measure(
        f"3d.mlp_device ({bucket} rows: the bucket)",
        lambda f: mlp_fn(estimator.params, feats_bucket[f]),
    )
    measure(
        f"3d.mlp_device ({n} rows: the people)", lambda f: mlp_fn(estimator.params, feats_exact[f])
    )
    measure("3d.mlp_device (1 row)", lambda f: mlp_fn(estimator.params, feats_exact[f][:1]))
    measure("3d.total", t_3dg)
    measure(f"3d.total after {IDLE_MS} ms idle", t_3dg, before=idle)
    return {
        "views": int(rig.num_cameras),
        "people": int(n),
        "model": size,
        "bucket": int(bucket),
        "graph_budgets": sorted({str(dataclasses.astuple(_budget(det, f))) for f in frames}),
        "mlp_bytes": param_bytes(estimator.params),
        "gat_bytes": param_bytes(matcher.params),
        "parts_ms": parts,
    }


# --------------------------------------------------------------------------- offline throughput


def offline(tier: Tier) -> dict:
    """A long recording in chunks, as `inference.stream_pipeline` runs it: both stages' frames/s
    and people/s, the 3D stage's GFLOP/s, and the single-person latency."""
    V, n, K = TARGET_VIEWS, TARGET_PEOPLE, 18
    rig, rec = scenes.recording(V, n, tier.offline_frames, seed=7)
    det, members = _numpy_detections(rec)
    F, C, P, _ = det.score.shape
    chunks = [slice(s, min(F, s + tier.offline_chunk)) for s in range(0, F, tier.offline_chunk)]
    chunk = lambda sl: Detections(det.xy[sl], det.score[sl], det.count[sl])  # noqa: E731
    out = {"views": V, "people": n, "frames": F, "chunk_frames": tier.offline_chunk, "models": {}}
    for size in tier.model_sizes:
        mlp, gat = scenes.MODEL_SIZES[size]
        matcher, estimator = scenes.matcher_for(rig, K, gat), scenes.estimator_for(rig, K, mlp)

        def stage2():  # stream_pipeline's proposal step, chunk by chunk
            return sum(
                len(p) for sl in chunks for p in propose_with_matcher(matcher, chunk(sl)).people
            )

        def stage3():  # its 3D step, on the true proposals
            return sum(
                int(
                    poses_of_members(rig, chunk(sl), members[sl], estimator=estimator)[
                        0
                    ].valid.sum()
                )
                for sl in chunks
            )

        def triangulation():
            return sum(
                int(poses_of_members(rig, chunk(sl), members[sl], method="dlt")[0].valid.sum())
                for sl in chunks
            )

        first2, _ = timed(stage2)
        first3, people = timed(stage3)
        t2 = repeat(stage2, n=tier.offline_repeats, warmup=0)
        t3 = repeat(stage3, n=tier.offline_repeats, warmup=0)
        flops = mlp_flops(estimator.params)
        t2m, t3m = float(np.median(t2)), float(np.median(t3))
        # The MLP alone on the people of one chunk (padded to its bucket), device-resident input.
        rows = next_power_of_two(tier.offline_chunk * n)
        feats = jnp.zeros((rows, C, K, 14), jnp.float32)
        mlp = jax.jit(lambda p, x: nnx.merge(estimator.graphdef, p, estimator.rest)(x))
        t_mlp = float(
            np.median(repeat(mlp, estimator.params, feats, n=max(2, tier.offline_repeats)))
        )
        # The features alone for one chunk's people (device-resident, padded to the same bucket).
        xy, score = group_people(det.xy[chunks[0]], det.score[chunks[0]], members[chunks[0]])
        xy, score = xy.reshape((-1,) + xy.shape[2:]), score.reshape((-1,) + score.shape[2:])
        pad = [(0, rows - len(xy))] + [(0, 0)] * 3
        xy_d, score_d = jnp.asarray(np.pad(xy, pad)), jnp.asarray(np.pad(score, pad[:-1]))
        feature_fn = jax.jit(
            lambda r, a, b: assemble_features(estimator_inputs(r, a, b), (b > 0).any(axis=-1))
        )
        t_feat = float(
            np.median(repeat(feature_fn, rig, xy_d, score_d, n=max(2, tier.offline_repeats)))
        )
        # Single-person latency: the library call with one person, and the MLP alone on one row.
        xy, score = group_people(det.xy[:1], det.score[:1], members[:1])
        single = repeat(predict_people, estimator, xy[0, :1], score[0, :1], n=tier.single_repeats)
        single_mlp = repeat(mlp, estimator.params, feats[:1], n=tier.single_repeats)
        entry = {
            "stage2": {
                "seconds": t2m,
                "first_run_seconds": first2,
                "frames_per_s": F / t2m,
                "people_per_s": F * n / t2m,
                "repeats": t2.size,
            },
            "stage3": {
                "seconds": t3m,
                "first_run_seconds": first3,
                "frames_per_s": F / t3m,
                "people_per_s": people / t3m,
                "people": people,
                "gflops": flops * people / t3m / 1e9,
                "repeats": t3.size,
            },
            "mlp_only": {
                "rows": rows,
                "seconds": t_mlp,
                "people_per_s": rows / t_mlp,
                "gflops": flops * rows / t_mlp / 1e9,
            },
            "features_only": {"rows": rows, "seconds": t_feat, "people_per_s": rows / t_feat},
            "chunks": len(chunks),
            "single_person": {
                "predict_people_ms": summary(single),
                "mlp_one_row_ms": summary(single_mlp),
            },
            "mlp_flops_per_person": flops,
            "mlp_bytes": param_bytes(estimator.params),
        }
        if size == tier.model_sizes[0]:
            first_t, _ = timed(triangulation)
            tt = float(np.median(repeat(triangulation, n=tier.offline_repeats, warmup=0)))
            entry["triangulation_dlt"] = {
                "seconds": tt,
                "frames_per_s": F / tt,
                "first_run_seconds": first_t,
            }
        out["models"][size] = entry
    return out


# --------------------------------------------------------------------------- training throughput


def training(tier: Tier) -> dict:
    """Samples/s and compile time of one train step of each model (panoptic5, single-person data)."""
    rig = load_rig(scenes.PANOPTIC)
    K = 18
    num_rec = 8  # the matcher composes up to 8 people from 8 different recordings
    recs = generate_single_person_recordings(
        rig, num_recordings=num_rec, num_frames=max(8, -(-tier.train_batch // num_rec) * 2), seed=3
    )
    xy, score = single_person_samples(recs)
    out = {"estimator": {}, "matcher": {}}
    for size in tier.model_sizes:
        mlp, gat = scenes.MODEL_SIZES[size]
        out["estimator"][size] = _train_estimator_step(rig, xy, score, mlp, tier)
        out["matcher"][size] = _train_matcher_step(rig, recs, gat, tier, K)
    return out


def _train_estimator_step(rig, xy, score, mlp, tier: Tier) -> dict:
    config = EstimatorConfig(mlp=mlp)
    setup = estimator_training(rig, config, xy.shape[-2])  # as train_estimator sets it up
    state, step = setup.state, setup.train_step
    data = setup.batches(xy, score)
    B = tier.train_batch
    rng = np.random.default_rng(0)
    key = jax.random.key(0)

    def batch():  # as train_estimator draws a batch: an index gather on the device
        idx = rng.choice(len(xy), B, replace=len(xy) < B)
        return jax.tree.map(lambda a: a[idx], data)

    b = batch()
    first, (state, _) = timed(step, state, b, key)
    times = []
    for _ in range(tier.train_steps):
        b = jax.block_until_ready(batch())
        t, (state, metrics) = timed(step, state, b, key)
        times.append(t)
    med = float(np.median(times))
    samples = B * (1 + config.num_augment)
    return {
        "batch": B,
        "augmented_per_seed": config.num_augment,
        "step_ms": summary(times),
        "seed_samples_per_s": B / med,
        "forward_backward_samples_per_s": samples / med,
        "compile_seconds": max(0.0, first - med),
        "first_step_seconds": first,
        "gflops": 3 * mlp_flops(state.params) * samples / med / 1e9,
    }


def _train_matcher_step(rig, recs, gat, tier: Tier, K: int) -> dict:
    config = MatcherConfig(gat=gat)
    per_batch = config.train.batch_size
    pool = make_pool(rig, recs)
    rng = np.random.default_rng(0)
    build_times, batches = [], []
    for _ in range(
        tier.matcher_batches
    ):  # as train_matcher's epoch_batches builds them, one at a time
        t, b = timed(
            lambda: sample_batches(pool, rng, 1, per_batch, max_people=config.max_people)[0]
        )
        build_times.append(t)
        batches.append(b)
    model = MatchingGAT(rig.num_cameras, K, gat, rngs=nnx.Rngs(0))
    tx = make_optimizer(config.train, config.steps_per_epoch)
    graphdef, rest, state = init_train_state(model, tx)
    step = make_train_step(graphdef, rest, tx, matcher_loss_fn, xla_kernels=True)
    key = jax.random.key(0)
    compile_times, seen = [], {}
    for b in batches:  # warm-up: one compilation per graph budget
        shape = (b.graphs.nodes.shape[0], b.det_features.shape[0])
        t, (state, _) = timed(step, state, b, key)
        if shape not in seen:
            seen[shape] = t
    times = []
    for i in range(max(tier.train_steps, len(batches))):
        t, (state, _) = timed(step, state, batches[i % len(batches)], key)
        times.append(t)
    steady = float(np.median(times))
    compile_times = [max(0.0, t - steady) for t in seen.values()]
    med_build = float(np.median(build_times))
    return {
        "graphs_per_batch": per_batch,
        "step_ms": summary(times),
        "graphs_per_s": per_batch / steady,
        "host_batch_ms": summary(build_times),
        "host_graphs_per_s": per_batch / med_build,
        "end_to_end_graphs_per_s": per_batch / (steady + med_build),
        "compile_seconds": float(np.mean(compile_times)),
        "budgets_compiled": len(seen),
        "budgets": [list(s) for s in seen],
    }


# --------------------------------------------------------------------------- tracking

TRACKING_LIMIT_MS = 0.1  # per person per frame, tracker + One-Euro (the tracker issue)


def tracking(tier: Tier) -> dict:
    """Per-frame host time of the streaming path after the 3D stage, per person.

    Each frame: `tracking.update_tracks` (with the 2D evidence of every camera) then
    `smoothing.one_euro_update`, as `inference.stream_pipeline` runs them. Input: the synthetic
    ground truth (5 views) with 1 cm noise, grouped by the true identities, so the person count
    is exact.
    """
    from mvpose_jax.smoothing import one_euro_initial, one_euro_update
    from mvpose_jax.synthetic import generate_recording
    from mvpose_jax.tracking import initial_state, metres_per_pixel, update_tracks

    people = (2,) if tier.name == "smoke" else (1, 4, 8, 16)
    frames = {"smoke": 10, "quick": 100, "full": 300}[tier.name]
    rig = load_rig("panoptic5")
    rows = []
    for n in people:
        rec = generate_recording(rig, num_people=n, num_frames=frames, seed=[0, 9, n])
        gt = rec.ground_truth
        xy, score = group_people(
            rec.detections.xy, rec.detections.score, members_from_identity(rec.identity, n)
        )
        rng = np.random.default_rng(n)
        xyz = np.asarray(gt.xyz, np.float64) + rng.normal(0, 0.01, np.shape(gt.xyz))
        kv = np.asarray(gt.keypoint_valid)
        centre = (xyz * kv[..., None]).sum(-2) / np.maximum(kv.sum(-1, keepdims=True), 1)
        per_px = metres_per_pixel(rig, centre)
        K, C = kv.shape[-1], rig.num_cameras
        track_s, euro_s = [], []
        for rep in range(2):  # the first pass warms up (imports, caches)
            state, euro = initial_state(K, C), one_euro_initial(K)
            for f in range(frames):
                t0 = time.perf_counter()
                state, ids = update_tracks(
                    state,
                    time=f / 30.0,
                    xyz=xyz[f],
                    keypoint_valid=kv[f],
                    xy=xy[f],
                    score=score[f],
                    metres_per_px=per_px[f],
                )
                t1 = time.perf_counter()
                # As the pipeline does: people on tentative tracks (-1) are not filtered.
                on = ids >= 0
                euro, _ = one_euro_update(
                    euro, time=f / 30.0, track=ids[on], xyz=xyz[f][on], keypoint_valid=kv[f][on]
                )
                t2 = time.perf_counter()
                if rep:
                    track_s.append(t1 - t0)
                    euro_s.append(t2 - t1)
        total = np.asarray(track_s) + np.asarray(euro_s)
        per_person = summary(total / n)
        rows.append(
            {
                "people": n,
                "frames": frames,
                "tracks": int(state.next_id),
                "tracker_ms": summary(track_s),
                "one_euro_ms": summary(euro_s),
                "per_person_ms": per_person,
                "status": "pass" if per_person["median"] <= TRACKING_LIMIT_MS else "miss",
            }
        )
    return {"limit_ms_per_person": TRACKING_LIMIT_MS, "rows": rows}


# --------------------------------------------------------------------------- infer memory


def infer_memory(tier: Tier) -> dict:
    """Peak RSS of ``mvpose-jax infer`` at each recording length (`benchmarks.memory`)."""
    return memory.infer_memory(
        tier.memory_frames, chunk_frames=tier.memory_chunk, whole_max_frames=tier.memory_whole_max
    )


# --------------------------------------------------------------------------- adapt


def adapt(tier: Tier) -> dict:
    """`adapt_estimator` on a recording of ``tier.adapt_frames`` frames (5 views, 4 people) with a
    quick-size MLP (`MLPConfig.quick()` with residual output and the experiments' recipe, as
    ``SCALES["quick"]`` trains it; random weights: the time does not depend on them), the
    epipolar proposals, and early stopping and the clock switched off so that every one of the
    default steps runs: the most an adaptation with the default settings costs."""
    V, n, K = TARGET_VIEWS, TARGET_PEOPLE, 18
    rig, rec = scenes.recording(V, n, tier.adapt_frames, seed=11)
    det, _ = _numpy_detections(rec)
    mlp = dataclasses.replace(scenes.MODEL_SIZES["quick"][0], output="residual")
    est = scenes.estimator_for(rig, K, mlp)
    est = est._replace(config=dataclasses.replace(est.config, loss_power=1.0))
    config = AdaptConfig(max_steps=tier.adapt_steps, max_seconds=1e9, patience=10**6)
    t0, cpu0 = time.perf_counter(), time.process_time()
    _, report = adapt_estimator(rig, det, est, config=config, progress=False)
    seconds, cpu = time.perf_counter() - t0, time.process_time() - cpu0
    F = report.frames
    training = seconds - report.seconds_grouping
    first_check = report.history[0] if report.history else {}
    per_1000 = 1000 * seconds / F
    # Its steps are a fixed number: a longer recording costs more only in its proposals.
    return {
        "views": V,
        "people": n,
        "frames": F,
        "people_adapt": report.people_adapt,
        "people_heldout": report.people_heldout,
        "steps": report.steps,
        "batch": config.batch_size,
        "seconds": seconds,
        # CPU time of every thread of the process: on a busy machine the wall time says more
        # about the other jobs; on an idle one with c cores it is at least cpu / c.
        "cpu_seconds": cpu,
        "grouping_seconds": report.seconds_grouping,
        "training_seconds": training,
        "ms_per_step_incl_compile_and_checks": 1000 * training / max(1, report.steps),
        "first_check_seconds": first_check.get("seconds"),
        "seconds_per_1000_frames": per_1000,
        "limit_seconds_per_1000_frames": SECONDS_PER_1000_FRAMES,
        "status": "pass" if per_1000 <= SECONDS_PER_1000_FRAMES else "miss",
    }


def pipeline_group(tier: Tier) -> dict:
    """What users run, timed through the public API (`benchmarks.pipeline`)."""
    from benchmarks import pipeline

    return pipeline.pipeline_group(tier.name)


def adapt_matcher_group(tier: Tier) -> dict:
    """`adapt_matcher` on the ``adapt`` group's recording (``tier.adapt_frames`` frames, 5 views,
    4 people) with the paper's GAT, which the experiments' quick scale trains (random weights),
    and the true groups as pair labels (the
    time depends on neither), early stopping and the clock switched off so that every one of the
    default steps runs: the most a matcher adaptation with the default settings costs (its
    proposals excluded: the labels are given)."""
    V, n, K = TARGET_VIEWS, TARGET_PEOPLE, 18
    rig, rec = scenes.recording(V, n, tier.adapt_frames, seed=11)
    det, _ = _numpy_detections(rec)
    matcher = scenes.matcher_for(rig, K, scenes.MODEL_SIZES["paper"][1])
    config = MatcherAdaptConfig(max_steps=tier.adapt_matcher_steps, max_seconds=1e9, patience=10**6)
    t0, cpu0 = time.perf_counter(), time.process_time()
    _, report = adapt_matcher(
        rig, det, matcher, identity=np.asarray(rec.identity), config=config, progress=False
    )
    seconds, cpu = time.perf_counter() - t0, time.process_time() - cpu0
    F = report.frames
    per_1000 = 1000 * seconds / F
    return {
        "views": V,
        "people": n,
        "frames": F,
        "frames_adapt": report.frames_adapt,
        "frames_heldout": report.frames_heldout,
        "pairs_adapt": report.pairs_adapt,
        "steps": report.steps,
        "batch_frames": config.batch_frames,
        "seconds": seconds,
        "cpu_seconds": cpu,
        "ms_per_step_incl_compile_and_checks": 1000 * seconds / max(1, report.steps),
        "seconds_per_1000_frames": per_1000,
        "limit_seconds_per_1000_frames": SECONDS_PER_1000_FRAMES,
        "status": "pass" if per_1000 <= SECONDS_PER_1000_FRAMES else "miss",
    }


def batch_group(tier: Tier) -> dict:
    """Many recordings on a local Ray, 1 and 2 workers (`benchmarks.batch`)."""
    from benchmarks import batch

    return batch.batch_group(tier.name)


GROUPS: dict[str, Callable[[Tier], dict]] = {
    "peaks": peaks,
    "latency": latency,
    "offline": offline,
    "training": training,
    "tracking": tracking,
    "infer_memory": infer_memory,
    "adapt": adapt,
    "adapt_matcher": adapt_matcher_group,
    "pipeline": pipeline_group,
    "batch": batch_group,
}
