"""The ``batch`` job: many recordings over a pool of Ray workers, each run as ``infer`` runs it.

`run_batch(BatchConfig) -> BatchResult` is what ``mvpose-jax batch`` runs; `run_generate_batch`
is ``generate --recordings N``. Both turn their input into `BatchTask` s (one per recording) and
hand them to `run_pool`:

- one Ray actor per worker (`PoolConfig.workers`, default one per ``cpus_per_worker`` CPUs of
  the cluster), a spawned process that imports JAX once, keeps its compiled functions and the
  models it loaded (`jobs.infer.load_models`) for every recording it runs, and has one XLA thread
  pool sized to its CPUs (``XLA_FLAGS`` in its ``runtime_env``);
- a batch run in a process that started Ray itself (`ray.init`: a notebook, an experiment, the
  tests) may keep its workers idle and warm for the process's next batch
  (`PoolConfig.keep_workers`; they hold their CPUs until `release_workers`); otherwise the
  workers end with the batch, and Ray too when the job started it;
- each worker is given one recording at a time, the next one as soon as it is done, so a long
  recording holds no other back;
- a worker runs `run_task`, the very code ``infer`` / ``infer --session`` / ``generate`` run, and
  writes the recording's results itself (atomically, as those jobs do) to its output folder, a
  path every worker sees (shared storage on a cluster) or an fsspec URL (``s3://bucket/run``:
  written locally, then uploaded file by file, `jobs.storage`);
- a worker that dies (killed, out of memory, its machine gone) is replaced and its recording is
  run again from its start, up to `PoolConfig.retries` times; a recording whose input is bad
  fails with the `errors.InputError` naming its file, frame, camera and field, and the others go
  on;
- the run manifest ``OUT/batch.json`` (`MANIFEST`, rewritten atomically after every recording)
  records each recording's status, error, output, attempts, frames and seconds; with ``resume``
  a recording recorded done, with the same settings and its output still there, is not run
  again.

Ray is imported here only, when a pool starts: the package installs and imports without it
(``pip install "mvpose-jax[cluster]"`` adds it).
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import os
import signal
import socket
import threading
import time
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NamedTuple

from mvpose_jax.data.files import to_jsonable
from mvpose_jax.data.pose2sim import Pose2SimTrial
from mvpose_jax.errors import InputError, MvposeError
from mvpose_jax.inference import PipelineConfig
from mvpose_jax.jobs import storage
from mvpose_jax.jobs.common import DetectionsSource, RigSource
from mvpose_jax.jobs.generate import GenerateConfig
from mvpose_jax.jobs.infer import INFER_PIPELINE, InferConfig
from mvpose_jax.jobs.session import SessionConfig

MANIFEST = "batch.json"
MANIFEST_FORMAT = "mvpose-jax.batch-run"
INSTALL_HINT = (
    'batch runs on Ray: pip install "mvpose-jax[cluster]" (or pip install "ray[default]")'
)

# Test hook, read by the driver and handed to the one task it names: "NAME=MARKER" makes the
# worker running recording NAME kill itself (SIGKILL) the first time, once the recording's first
# chunk is written, creating MARKER so that the retry runs. It stands for a machine that dies
# mid-recording.
KILL_ONCE_ENV = "MVPOSE_JAX_TEST_KILL_WORKER"


@dataclasses.dataclass(frozen=True)
class PoolConfig:
    """The Ray workers.

    Attributes:
      address: the Ray cluster to join (``ray start --head`` prints it; "auto": the one this
        machine belongs to); None: a Ray already started in this process, else a local one on
        this machine's CPUs (stopped at the end).
      workers: how many workers (None: the cluster's CPUs / ``cpus_per_worker``, at most one per
        recording).
      cpus_per_worker: CPUs each worker reserves; its XLA thread pool has as many threads.
      retries: how many times a recording whose worker died is run again.
      keep_workers: with a Ray this process started itself, keep the workers after the batch,
        idle and warm (JAX imported, functions compiled, models loaded), for its next batch;
        they hold their CPUs until `release_workers`.
    """

    address: str | None = None
    workers: int | None = None
    cpus_per_worker: int = 1
    retries: int = 2
    keep_workers: bool = False


@dataclasses.dataclass(frozen=True)
class BatchConfig:
    """One ``batch`` run.

    Attributes:
      source: a Pose2Sim project (session, participant or trial folder: every trial, as
        ``infer --session``), a folder of recordings (every .json, .npz and OpenPose folder in
        it, recursively; ``rig`` their calibration) or a manifest file (`read_manifest_file`).
      out: the output folder (a path, or an fsspec URL such as ``s3://bucket/run``):
        ``out/<trial>/`` per Pose2Sim trial, ``out/<path in the folder without its suffix>/``
        per recording of a folder, the manifest file's outputs relative to it; and the run
        manifest ``out/batch.json``.
      rig: the calibration of a folder's recordings (a manifest file names its own).
      pipeline, matcher, estimator, fps, keep_chunks: as `jobs.infer.InferConfig`'s, for every
        recording.
      layout: the keypoint layout to work in (None: the file's; coco18 for a Pose2Sim project).
      trc: Pose2Sim projects: also write Pose2Sim-named TRC files (as ``infer --session``).
      resume: skip the recordings the run manifest records as done (same settings, output
        there); the others continue their own unfinished ``infer`` run, if any.
      pool: the Ray workers.
      progress: a progress bar across recordings, with frames/s.
    """

    source: str
    out: str
    rig: RigSource | None = None
    pipeline: PipelineConfig = INFER_PIPELINE
    matcher: str | None = None
    estimator: str | None = None
    layout: str | None = None
    fps: float | None = None
    trc: bool = True
    resume: bool = False
    keep_chunks: bool = False
    pool: PoolConfig = PoolConfig()
    progress: bool = True


@dataclasses.dataclass(frozen=True)
class TrialJob:
    """One trial of a Pose2Sim project, run as ``infer --session`` runs it (`session.run_trial`)."""

    session: SessionConfig
    trial: Pose2SimTrial


@dataclasses.dataclass(frozen=True)
class BatchTask:
    """One recording of a batch.

    Attributes:
      name: unique in the batch; the run manifest's key.
      out: where its results go (a folder, or the file of a generated recording).
      job: what runs: an ``infer`` run, a Pose2Sim trial or a ``generate`` run.
      kill_marker: test hook (`KILL_ONCE_ENV`): the worker kills itself unless this file exists.
    """

    name: str
    out: str
    job: InferConfig | TrialJob | GenerateConfig
    kill_marker: str | None = None


class RecordingStatus(NamedTuple):
    """One recording's outcome: status "done", "failed", "skipped" (done by an earlier run,
    resumed) or "pending" (not run: the driver was interrupted); error: why it failed (an
    `InputError` names file, frame, camera and field); attempts: runs started (a dead worker's
    included); frames: frames computed or generated; seconds: the last attempt's wall time;
    worker: "host:pid" of the worker that finished it."""

    name: str
    status: str
    out: str
    error: str | None = None
    attempts: int = 0
    frames: int = 0
    seconds: float = 0.0
    worker: str | None = None


class BatchResult(NamedTuple):
    """What a batch did: every recording's `RecordingStatus` (in the batch's order), the run
    manifest written, the workers used, the wall time (s), whether the driver was interrupted
    (Ctrl-C), and the seconds from the pool's start until its last new worker had started and
    imported JAX (None: no new worker, all taken warm from an earlier batch)."""

    recordings: tuple[RecordingStatus, ...]
    manifest: Path | str
    workers: int
    seconds: float
    interrupted: bool = False
    startup_s: float | None = None

    @property
    def failed(self) -> tuple[RecordingStatus, ...]:
        return tuple(r for r in self.recordings if r.status == "failed")

    @property
    def frames(self) -> int:
        """Frames computed by this run (skipped recordings not counted)."""
        return sum(r.frames for r in self.recordings if r.status == "done")


def run_batch(
    config: BatchConfig, *, on_done: Callable[[RecordingStatus], None] = lambda status: None
) -> BatchResult:
    """Runs every recording of ``config.source`` on the pool (the module docstring);
    ``on_done`` is called on the driver as each recording ends.

    Raises:
      InputError: a source that holds no recording, a bad manifest file (named), two
        recordings with one name. A recording's own bad input is not raised: it is in its
        status (and the manifest).
      MvposeError: Ray is not installed (the message says how to install it).
    """
    return run_pool(
        batch_tasks(config),
        config.out,
        config.pool,
        resume=config.resume,
        progress=config.progress,
        on_done=on_done,
        source=str(config.source),
    )


def run_generate_batch(
    config: GenerateConfig,
    recordings: int,
    pool: PoolConfig = PoolConfig(),
    *,
    single_person: bool = False,
    resume: bool = False,
    progress: bool = True,
    on_done: Callable[[RecordingStatus], None] = lambda status: None,
) -> BatchResult:
    """``generate --recordings N``: N recordings written into the folder ``config.out`` as
    ``recording_<i>.<json|npz>`` (``config.format``), recording i exactly what `generate` writes
    with ``seed = config.seed + i``: a scene of ``config.people``, or with ``single_person`` a
    training recording of one person (the floor jittered as `generate`'s single-person
    recordings are), whatever the number of workers. The run manifest is ``out/batch.json``.
    """
    from mvpose_jax.data.files import check_writable

    if recordings < 1:
        raise InputError(f"must be at least 1, not {recordings}", field="--recordings")
    if config.single_person_recordings:
        raise InputError(
            "one scene per recording: give --recordings N (with --single-person for training "
            "recordings), not --single-person-recordings too",
            field="--single-person-recordings",
        )
    out = config.out if storage.is_url(config.out) else check_writable(config.out, folder=True)
    suffix = ".npz" if config.format == "npz" else ".json"
    jitter = config.floor_jitter
    if single_person and jitter is None:
        from mvpose_jax.jobs.generate import TRAINING_FLOOR_JITTER_M

        jitter = TRAINING_FLOOR_JITTER_M
    width = len(str(recordings - 1))
    tasks = []
    for i in range(recordings):
        name = f"recording_{i:0{width}d}"
        path = storage.join(out, name + suffix)
        job = dataclasses.replace(
            config,
            out=path,
            seed=config.seed + i,
            people=1 if single_person else config.people,
            floor_jitter=jitter,
        )
        tasks.append(BatchTask(name, path, job))
    return run_pool(
        tasks, out, pool, resume=resume, progress=progress, on_done=on_done, source="generate"
    )


# ------------------------------------------------------------------------------ the recordings


def batch_tasks(config: BatchConfig) -> list[BatchTask]:
    """The recordings of ``config.source``, one `BatchTask` each (`BatchConfig.source`)."""
    from mvpose_jax.data.pose2sim import find_trials, is_pose2sim_project

    source = Path(config.source)
    if not source.exists():
        raise InputError("no such file or folder", file=source, field="source")
    if is_pose2sim_project(source):
        if config.rig is not None:
            raise InputError(
                "a Pose2Sim project's calibration is found in it: leave --rig out", field="--rig"
            )
        session = SessionConfig(
            str(source),
            config.out,
            config.pipeline,
            matcher=config.matcher,
            estimator=config.estimator,
            layout=config.layout,
            fps=config.fps,
            trc=config.trc,
            resume=config.resume,
            keep_chunks=config.keep_chunks,
            progress=False,
        )
        tasks = [
            BatchTask(t.name, storage.join(config.out, t.name), TrialJob(session, t))
            for t in find_trials(source).trials
        ]
    elif source.is_file():
        tasks = [
            _infer_task(config, name, rig, recording, out)
            for name, recording, rig, out in read_manifest_file(source, config.out)
        ]
    else:
        if config.rig is None:
            raise InputError("give the calibration of the folder's recordings", field="--rig")
        tasks = []
        for path in _recordings_under(source):
            name = path.relative_to(source).with_suffix("").as_posix()
            out = storage.join(config.out, name)
            tasks.append(_infer_task(config, name, config.rig, str(path), out))
    names = [t.name for t in tasks]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise InputError(
            f"recordings named alike would share an output: {', '.join(twice)}", file=source
        )
    return tasks


def read_manifest_file(path: str | os.PathLike, out: str) -> list[tuple[str, str, RigSource, str]]:
    """A manifest file's recordings: (name, recording, calibration, output folder) per line.

    Each line is ``RECORDING CALIBRATION [OUTPUT]``, separated by tabs when the line has any
    (paths with spaces), else by spaces; blank lines and lines starting with ``#`` are skipped.
    A relative recording or calibration path is relative to the manifest file's folder (a
    calibration that is no file there is taken as given: a preset name), a relative output to
    ``out``; no output: ``out/<the recording's name without its suffix>``.
    The name of a recording is its output relative to ``out``.
    """
    path = Path(path)
    base = path.parent
    rows = []
    text = path.read_text(encoding="utf-8", errors="replace")
    for n, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = [p.strip() for p in line.split("\t")] if "\t" in line else line.split()
        if len(parts) not in (2, 3):
            raise InputError(
                f"line {n} holds {len(parts)} fields: give RECORDING CALIBRATION [OUTPUT]",
                file=path,
                field=f"line {n}",
            )
        recording = str(base / parts[0])
        # A calibration file relative to the manifest, else as given (a preset name: panoptic5).
        calibration = base / parts[1] if (base / parts[1]).exists() else Path(parts[1])
        output = parts[2] if len(parts) == 3 else Path(parts[0]).with_suffix("").name
        rows.append(
            (
                Path(output).as_posix(),
                recording,
                RigSource(str(calibration)),
                storage.join(out, output),
            )
        )
    if not rows:
        raise InputError("lists no recording", file=path)
    return rows


def _infer_task(config: BatchConfig, name: str, rig: RigSource, recording: str, out: str):
    infer = InferConfig(
        rig,
        DetectionsSource(recording, layout=config.layout),
        out,
        config.pipeline,
        matcher=config.matcher,
        estimator=config.estimator,
        fps=config.fps,
        resume=config.resume,
        keep_chunks=config.keep_chunks,
        progress=False,
    )
    return BatchTask(name, out, infer)


def _recordings_under(folder: Path) -> list[Path]:
    """Every .json / .npz file and OpenPose folder under ``folder``, sorted."""
    from mvpose_jax.data.openpose import is_openpose_folder

    def found(f: Path):
        if is_openpose_folder(f):
            yield f
            return
        for p in sorted(f.iterdir()):
            if p.is_dir():
                yield from found(p)
            elif p.suffix.lower() in (".npz", ".json"):
                yield p

    paths = list(found(folder))
    if not paths:
        raise InputError("no recordings (.npz, .json or OpenPose folders) here", file=folder)
    return paths


# ---------------------------------------------------------------------------------- one task


def run_task(task: BatchTask, models: dict | None = None) -> dict[str, Any]:
    """Runs one recording in this process, as ``infer`` / ``infer --session`` / ``generate``
    would, and says how it went: {"status": "done" | "failed", "error", "frames", "seconds",
    "worker"}. Bad input (an `MvposeError`) and any other exception fail the recording without
    raising; a worker runs this, ``models`` its cache of loaded models (`infer.load_models`).
    An output at a URL is written into a local staging folder, then uploaded
    (`storage.publish`); its ``infer`` run starts from its first frame."""
    start = time.perf_counter()
    worker = f"{socket.gethostname()}:{os.getpid()}"
    try:
        with storage.staging(task.out) as folder:
            job, local = (task.job, task.out) if folder is None else _staged(task, folder)
            frames = _run_job(job, models, task.kill_marker, local)
            if folder is not None:
                storage.publish(local, task.out)
    except MvposeError as e:
        return _status("failed", str(e), 0, start, worker)
    except Exception as e:  # a bug, named: it must not stop the other recordings
        return _status("failed", f"{type(e).__name__}: {e}", 0, start, worker)
    return _status("done", None, frames, start, worker)


def _staged(task: BatchTask, folder: Path) -> tuple[InferConfig | TrialJob | GenerateConfig, str]:
    """``task``'s job writing into the local ``folder`` instead of its URL, and where in it the
    results then are (a folder, or a generated recording's file)."""
    job = task.job
    if isinstance(job, TrialJob):
        session = dataclasses.replace(job.session, out=str(folder), resume=False)
        return TrialJob(session, job.trial), str(folder / job.trial.name)
    local = str(folder / task.out.rstrip("/").rsplit("/", 1)[-1])
    if isinstance(job, InferConfig):
        return dataclasses.replace(job, out=local, resume=False), local
    return dataclasses.replace(job, out=local), local


def _run_job(job, models: dict | None, kill_marker: str | None, out: str) -> int:
    """Runs one recording's job, its results written to ``out``; returns its frames."""
    from mvpose_jax.jobs.generate import generate
    from mvpose_jax.jobs.infer import run_infer
    from mvpose_jax.jobs.session import run_trial

    die = None
    if kill_marker is not None and not os.path.exists(kill_marker):
        die = _die_mid_recording(job, kill_marker, out)
    if isinstance(job, TrialJob):
        result = run_trial(job.session, job.trial, models=models).result
        frames = result.frames
    elif isinstance(job, InferConfig):
        result = run_infer(job, models=models)
        frames = result.frames
    else:
        made = generate(job)
        frames = made.frames * made.recordings
    if not isinstance(job, GenerateConfig) and result.interrupted:
        raise MvposeError("interrupted")
    if die is not None:  # the recording ended before the hook saw a chunk: die now
        die()
    return frames


def _die_mid_recording(job, kill_marker: str, out: str) -> Callable[[], None]:
    """Test hook (`KILL_ONCE_ENV`): this process SIGKILLs itself once the recording's first chunk
    is on disk (a generated recording: at once), the marker written first (one that cannot be
    written makes a worker that dies every time). Returns the kill, for a recording that ends
    before its watcher sees a chunk. The marker holds the pid and when it died."""

    def die(when: str = "at its end") -> None:
        with contextlib.suppress(OSError):
            Path(kill_marker).write_text(f"{os.getpid()} {when}\n")
        os.kill(os.getpid(), signal.SIGKILL)

    if isinstance(job, GenerateConfig):
        die("at its start")

    def watch() -> None:
        chunks = Path(out) / "chunks"
        while not any(chunks.glob("chunk_*.npz")):
            time.sleep(0.002)
        die("mid-recording")

    threading.Thread(target=watch, daemon=True).start()
    return die


def _status(status: str, error: str | None, frames: int, start: float, worker: str) -> dict:
    seconds = time.perf_counter() - start
    return {
        "status": status,
        "error": error,
        "frames": frames,
        "seconds": seconds,
        "worker": worker,
    }


class _Worker:
    """A Ray actor's body: one process that runs recordings one after the other (its JAX, its
    compiled functions and its loaded models kept between them)."""

    def __init__(self) -> None:
        self.models: dict = {}

    def ready(self) -> float:
        """When (``time.time()``) this worker had started and imported JAX: the start-up cost,
        paid before its first recording."""
        import jax

        from mvpose_jax.compiled import enable_compilation_cache

        # On the driver's machine the driver's folder (inherited); on another, that one's own.
        enable_compilation_cache()
        jax.devices()
        return time.time()

    def run(self, task: BatchTask) -> dict[str, Any]:
        return run_task(task, self.models)


# ------------------------------------------------------------------------------------ the pool


def task_settings(task: BatchTask) -> str:
    """A digest of what makes a recording's results (its job's config, resume and progress
    aside): a resumed batch skips a done recording only when it is unchanged."""
    job = task.job
    if isinstance(job, InferConfig):
        job = dataclasses.replace(job, resume=False, progress=True)
    elif isinstance(job, TrialJob):
        job = TrialJob(dataclasses.replace(job.session, resume=False), job.trial)
    doc = json.dumps(to_jsonable(dataclasses.asdict(job)), sort_keys=True, default=str)
    return hashlib.sha256(f"{task.out}\n{doc}".encode()).hexdigest()[:16]


def xla_env(cpus: int) -> dict[str, str]:
    """A worker's environment: one XLA CPU thread pool of ``cpus`` threads (and as many for
    the BLAS / OpenMP libraries), so that workers sharing a machine do not oversubscribe it."""
    flags = os.environ.get("XLA_FLAGS", "")
    flags = " ".join(
        f
        for f in flags.split()
        if not f.startswith(("--xla_cpu_multi_thread_eigen", "intra_op_parallelism_threads"))
    )
    ours = f"--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads={cpus}"
    threads = str(cpus)
    return {
        "XLA_FLAGS": f"{flags} {ours}".strip(),
        "OMP_NUM_THREADS": threads,
        "OPENBLAS_NUM_THREADS": threads,
        "MKL_NUM_THREADS": threads,
    }


def run_pool(
    tasks: Sequence[BatchTask],
    out: str | os.PathLike,
    pool: PoolConfig,
    *,
    resume: bool = False,
    progress: bool = True,
    on_done: Callable[[RecordingStatus], None] = lambda status: None,
    source: str = "",
) -> BatchResult:
    """Runs ``tasks`` on Ray workers (the module docstring), the run manifest in ``out`` (a
    folder, or an fsspec URL)."""
    try:
        import ray
    except ImportError:
        raise MvposeError(INSTALL_HINT) from None
    from mvpose_jax.progress import progress_bar

    if pool.cpus_per_worker < 1:
        raise InputError("must be at least 1", field="--cpus-per-worker")
    if pool.workers is not None and pool.workers < 1:
        raise InputError("must be at least 1", field="--workers")
    if pool.retries < 0:
        raise InputError("must be >= 0", field="--retries")
    started = time.perf_counter()
    storage.make_folder(out)
    manifest = storage.join(out, MANIFEST)
    if not storage.is_url(manifest):
        manifest = Path(manifest)
    settings = {t.name: task_settings(t) for t in tasks}
    earlier = _read_manifest(manifest) if resume else {}
    status: dict[str, RecordingStatus] = {}
    todo: list[BatchTask] = []
    kill = _kill_hook()
    for t in tasks:
        was = earlier.get(t.name, {})
        if (
            was.get("status") in ("done", "skipped")
            and was.get("settings") == settings[t.name]
            and storage.exists(t.out)
        ):
            status[t.name] = RecordingStatus(
                t.name, "skipped", t.out, None, int(was.get("attempts", 0))
            )
        else:
            status[t.name] = RecordingStatus(t.name, "pending", t.out)
            if kill and kill[0] == t.name:
                t = dataclasses.replace(t, kill_marker=kill[1])
            todo.append(t)

    def write_manifest() -> None:
        doc = {
            "format": MANIFEST_FORMAT,
            "version": 1,
            "source": source,
            "recordings": {
                name: {**s._asdict(), "settings": settings[name]} for name, s in status.items()
            },
        }
        storage.write_text(manifest, json.dumps(to_jsonable(doc), indent=1) + "\n")

    write_manifest()
    if not todo:
        return BatchResult(tuple(status[t.name] for t in tasks), manifest, 0, 0.0)
    ours = not ray.is_initialized()
    if ours:
        with warnings.catch_warnings():
            # Ray starts its processes with fork + exec, which runs none of this process's
            # threads: JAX's warning about forking a threaded process does not apply.
            warnings.filterwarnings("ignore", "os.fork", RuntimeWarning)
            ray.init(
                address=pool.address,
                include_dashboard=False,
                log_to_driver=False,
                configure_logging=False,
            )
    interrupted = False
    workers = 0
    wall_start = time.time()
    ready: list = []
    try:
        cpus = int(ray.cluster_resources().get("CPU", 1))
        workers = pool.workers or max(1, cpus // pool.cpus_per_worker)
        workers = max(1, min(workers, len(todo)))
        env = xla_env(pool.cpus_per_worker)
        actor = ray.remote(num_cpus=pool.cpus_per_worker, max_restarts=0, max_task_retries=0)(
            _Worker
        ).options(runtime_env={"env_vars": env})
        context = ray.get_runtime_context()
        key = (context.get_node_id(), context.get_job_id(), tuple(sorted(env.items())))
        for stale in [k for k in _IDLE if k[:2] != key[:2]]:  # of a Ray since stopped
            del _IDLE[stale]
        idle = [] if ours else _IDLE.setdefault(key, [])

        def new_worker():
            if idle:
                return idle.pop()
            worker = actor.remote()
            ready.append(worker.ready.remote())
            return worker

        def release(worker) -> None:
            if pool.keep_workers and not ours:  # kept for this process's next batch, warm
                idle.append(worker)
            else:
                ray.kill(worker, no_restart=True)

        bar = progress_bar(
            total=len(tasks),
            initial=len(tasks) - len(todo),
            desc="recordings",
            unit="recording",
            disable=not progress,
        )
        queue = list(todo)
        attempts = {t.name: 0 for t in todo}
        running: dict[Any, tuple[Any, BatchTask]] = {}
        frames = 0

        def submit(worker) -> None:
            task = queue.pop(0)
            attempts[task.name] += 1
            status[task.name] = status[task.name]._replace(
                status="running", attempts=attempts[task.name]
            )
            running[worker.run.remote(task)] = (worker, task)

        for _ in range(workers):
            if queue:
                submit(new_worker())
        write_manifest()
        try:
            while running:
                [ref], _ = ray.wait(list(running), num_returns=1)
                worker, task = running.pop(ref)
                try:
                    got = ray.get(ref)
                except ray.exceptions.RayActorError as e:  # the worker died: a fresh one
                    ray.kill(worker, no_restart=True)
                    worker = new_worker() if queue or attempts[task.name] <= pool.retries else None
                    if attempts[task.name] <= pool.retries:
                        queue.insert(0, _from_start(task))
                        status[task.name] = status[task.name]._replace(status="pending")
                    else:
                        why = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
                        done = status[task.name]._replace(
                            status="failed",
                            error=f"its worker died {attempts[task.name]} times (last: {why})",
                        )
                        status[task.name] = done
                        bar.update(1)
                        on_done(done)
                except ray.exceptions.RayError as e:  # not the recording's: Ray's own error
                    got = {"status": "failed", "error": f"{type(e).__name__}: {e}"}
                    done = status[task.name]._replace(**got)
                    status[task.name] = done
                    bar.update(1)
                    on_done(done)
                else:
                    done = status[task.name]._replace(**got)
                    status[task.name] = done
                    frames += done.frames
                    bar.update(1)
                    elapsed = max(time.perf_counter() - started, 1e-9)
                    bar.set_postfix(frames_per_s=f"{frames / elapsed:.1f}", failed=_failed(status))
                    on_done(done)
                write_manifest()
                if queue:
                    submit(worker)
                elif worker is not None:
                    release(worker)
        except KeyboardInterrupt:
            interrupted = True
            for worker, task in running.values():
                ray.kill(worker, no_restart=True)
                status[task.name] = status[task.name]._replace(status="pending")
            write_manifest()
        finally:
            bar.close()
        started_at = []
        for ref in ready:
            try:
                started_at.append(ray.get(ref, timeout=0))
            except Exception:  # a worker that died or never started: no time to take
                continue
        startup = max(started_at) - wall_start if started_at else None
    finally:
        if ours:
            ray.shutdown()
    return BatchResult(
        tuple(status[t.name] for t in tasks),
        manifest,
        workers,
        time.perf_counter() - started,
        interrupted,
        startup,
    )


def _from_start(task: BatchTask) -> BatchTask:
    """``task`` run again from its first frame (not continuing the chunks its dead worker
    wrote): its results are then those of a run that never failed."""
    job = task.job
    if isinstance(job, InferConfig):
        job = dataclasses.replace(job, resume=False)
    elif isinstance(job, TrialJob):
        job = TrialJob(dataclasses.replace(job.session, resume=False), job.trial)
    return dataclasses.replace(task, job=job)


# Workers kept between this process's batches (`PoolConfig.keep_workers`) with their JAX,
# compiled functions and models warm: (driver's node, job, worker environment) -> idle actors.
_IDLE: dict[tuple, list] = {}


def release_workers() -> int:
    """Stops the workers kept idle by earlier batches (`PoolConfig.keep_workers`), freeing their
    CPUs; returns how many."""
    workers = [w for idle in _IDLE.values() for w in idle]
    _IDLE.clear()
    if workers:
        import ray

        if ray.is_initialized():
            for worker in workers:
                ray.kill(worker, no_restart=True)
    return len(workers)


def _failed(status: dict[str, RecordingStatus]) -> int:
    return sum(s.status == "failed" for s in status.values())


def _kill_hook() -> tuple[str, str] | None:
    value = os.environ.get(KILL_ONCE_ENV)
    if not value or "=" not in value:
        return None
    name, marker = value.split("=", 1)
    return name, marker


def _read_manifest(path: Path | str) -> dict[str, dict]:
    """The recordings of an earlier run's manifest (empty when there is none)."""
    if not storage.exists(path):
        return {}
    doc = storage.read_json_at(path)
    if not isinstance(doc, dict) or doc.get("format") != MANIFEST_FORMAT:
        raise InputError("not a batch run manifest", file=path, field="format")
    recordings = doc.get("recordings")
    return recordings if isinstance(recordings, dict) else {}
