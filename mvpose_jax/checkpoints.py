"""Orbax checkpoints of a training run: best and latest states, each with the run's config.

The only orbax import of the package. Training saves whole `TrainState`s (parameters,
optimiser state, step) so a killed run resumes exactly; inference restores the parameters alone
(`Checkpoints.restore_params`, a partial restore), so loading a model needs no optimiser.
`TrainState` is defined here, with what holds it, so that neither `train` (which steps it) nor
`trained` (which saves adapted parameters as one) is needed to read or write a checkpoint.
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any, NamedTuple

import jax
import numpy as np

from mvpose_jax.errors import InputError


class TrainState(NamedTuple):
    """Everything that changes during training (what a checkpoint holds)."""

    step: jax.Array  # () int32
    params: Any  # nnx.State: the trainable nnx.Param leaves
    opt_state: Any  # optax.OptState (() in a folder of parameters alone)


class Checkpoints:
    """Best and latest checkpoints of a run (orbax), each with the run's config as JSON.

    ``directory/best`` keeps the state with the lowest validation loss; ``directory/latest`` the
    ``max_to_keep`` newest states, each with the fit loop's own state (`FitProgress`, item
    ``fit``) so that a run continues exactly. Every checkpoint is written atomically by orbax (a
    temporary folder, renamed when complete): a run killed while saving leaves the previous
    checkpoints intact. Reading a damaged or mismatched checkpoint raises `InputError`.
    """

    def __init__(self, directory: str | Path, *, max_to_keep: int = 3):
        import orbax.checkpoint as ocp

        self._ocp = ocp
        self.directory = Path(directory).absolute()
        opts = dict(enable_async_checkpointing=False)

        # Handlers named up front (not only item names): the state's array metadata can then be
        # read before a restore, to refuse another model's checkpoint without reading its arrays.
        def handlers(*json_items):
            return {
                "state": ocp.StandardCheckpointHandler(),
                **{k: ocp.JsonCheckpointHandler() for k in json_items},
            }

        self.best = ocp.CheckpointManager(
            self.directory / "best",
            options=ocp.CheckpointManagerOptions(
                max_to_keep=1, best_fn=lambda m: m["val_loss"], best_mode="min", **opts
            ),
            item_handlers=handlers("config"),
        )
        self.latest = ocp.CheckpointManager(
            self.directory / "latest",
            options=ocp.CheckpointManagerOptions(max_to_keep=max(1, max_to_keep), **opts),
            item_handlers=handlers("config", "fit"),
        )

    def _args(self, state, config, progress=None):
        ocp = self._ocp
        items = dict(state=ocp.args.StandardSave(state), config=ocp.args.JsonSave(config))
        if progress is not None:
            items["fit"] = ocp.args.JsonSave(progress)
        return ocp.args.Composite(**items)

    def save_latest(self, state: TrainState, config: dict, progress: dict | None = None) -> None:
        """Saves ``state`` (and the fit loop's ``progress``, `FitProgress.to_json`) as the newest."""
        step = int(state.step)
        if step in self.latest.all_steps():
            self.latest.delete(step)  # the newer call knows more (e.g. the validation it just ran)
        self.latest.save(step, args=self._args(state, config, progress), force=True)

    def save_best(self, state: TrainState, config: dict, val_loss: float) -> None:
        step = int(state.step)
        if step in self.best.all_steps():
            return  # a resumed run passing the step again: the same state (runs are deterministic)
        self.best.save(
            step, args=self._args(state, config), metrics={"val_loss": float(val_loss)}, force=True
        )

    def restore(
        self, abstract_state: TrainState, which: str = "best", step: int | None = None
    ) -> tuple[TrainState, dict]:
        """Restores ``which`` ("best" or "latest"; its newest, or ``step``) against an abstract target.

        Raises:
          InputError when there is no such checkpoint, it holds another model (shapes differ) or
          it cannot be read (damaged files).
        """
        ocp = self._ocp
        manager, step = self._step(which, step)
        self._check_shapes(manager, step, which, abstract_state)
        args = ocp.args.Composite(
            state=ocp.args.StandardRestore(abstract_state), config=ocp.args.JsonRestore()
        )
        out = self._read(manager, step, which, args)
        state = out.state
        if all(getattr(a, "sharding", None) is None for a in jax.tree.leaves(abstract_state)):
            state = jax.device_put(state)  # committed, like `init_train_state` (no recompile)
        return state, dict(out.config)

    def restore_params(self, abstract_params, which: str = "best", step: int | None = None):
        """Restores the trained parameters alone (no optimiser state, no optimiser needed).

        Args:
          abstract_params: the model's parameters (`nnx.State`) or their shapes, the target.
        Returns:
          the parameters, committed to the default device.
        Raises:
          InputError as `restore`.
        """
        ocp = self._ocp
        manager, step = self._step(which, step)
        self._check_shapes(manager, step, which, {"params": abstract_params}, only="params")
        restore_args = jax.tree.map(
            lambda _: ocp.RestoreArgs(restore_type=np.ndarray), abstract_params
        )
        args = ocp.args.PyTreeRestore(
            item={"params": abstract_params},
            restore_args={"params": restore_args},
            partial_restore=True,
        )
        path = self.directory / which / str(step) / "state"
        try:
            out = ocp.PyTreeCheckpointer().restore(path, args=args)
        except Exception as e:  # orbax and tensorstore raise bare Exception on damaged files
            raise self._read_error(e, which, step) from e
        return jax.device_put(out["params"])

    def read_config(self, which: str = "best", step: int | None = None) -> dict:
        """The run config saved with the ``which`` checkpoint (to rebuild the model first)."""
        manager, step = self._step(which, step)
        out = self._read(
            manager, step, which, self._ocp.args.Composite(config=self._ocp.args.JsonRestore())
        )
        return dict(out.config)

    def read_progress(self, step: int | None = None) -> dict | None:
        """The fit loop's state saved with a latest checkpoint (None: a checkpoint without one)."""
        manager, step = self._step("latest", step)
        if not (self.directory / "latest" / str(step) / "fit").exists():
            return None
        out = self._read(
            manager, step, "latest", self._ocp.args.Composite(fit=self._ocp.args.JsonRestore())
        )
        return dict(out.fit)

    def close(self) -> None:
        self.best.close()
        self.latest.close()

    def _step(self, which: str, step: int | None):
        manager = self.best if which == "best" else self.latest
        if step is None:
            step = manager.best_step() if which == "best" else manager.latest_step()
        if step is None:
            raise InputError(f"no {which} checkpoint", file=self.directory / which)
        return manager, step

    def _check_shapes(
        self, manager, step: int, which: str, abstract_state, only: str | None = None
    ) -> None:
        try:
            meta = manager.item_metadata(step)["state"]
            saved = {
                _path_names(p): tuple(m.shape)
                for p, m in jax.tree_util.tree_flatten_with_path(meta)[0]
                if hasattr(m, "shape")
            }
            if only is not None:
                saved = {k: v for k, v in saved.items() if k[0] == only}
        except Exception:  # unreadable metadata: the restore itself reports the damage
            return
        wanted = {
            _path_names(p): tuple(a.shape)
            for p, a in jax.tree_util.tree_flatten_with_path(abstract_state)[0]
        }
        if not saved or saved == wanted:
            return
        diff = [
            f"{'.'.join(k)}: checkpoint {saved.get(k, 'absent')}, model {wanted.get(k, 'absent')}"
            for k in sorted(
                set(saved) | set(wanted), key=lambda k: (k[0] != "params", k)
            )  # params first
            if saved.get(k) != wanted.get(k)
        ]
        raise InputError(
            f"checkpoint holds another model ({'; '.join(diff[:3])}{'; ...' if len(diff) > 3 else ''})",
            file=self.directory / which / str(step),
        )

    def _read(self, manager, step: int, which: str, args):
        try:
            return manager.restore(step, args=args)
        except Exception as e:  # orbax and tensorstore raise bare Exception on damaged files
            raise self._read_error(e, which, step) from e

    def _read_error(self, e: Exception, which: str, step: int) -> InputError:
        detail = f"{type(e).__name__}: {str(e).splitlines()[0][:300] if str(e) else ''}"
        if "not compatible with the stored shape" in str(e):
            reason = "checkpoint holds another model (array shapes differ; "
        else:
            reason = "checkpoint is damaged or unreadable ("
            reason += "" if which == "best" else "delete this step's folder to use the one before; "
        return InputError(f"{reason}{detail})", file=self.directory / which / str(step))


def _path_names(path) -> tuple[str, ...]:
    """A pytree path as plain names (attribute, key or index), comparable across containers."""
    return tuple(str(getattr(k, "name", getattr(k, "key", getattr(k, "idx", k)))) for k in path)


def save_params_folder(
    folder: str | Path, params, config: dict, files: dict[str, str], val_loss: float = 0.0
) -> Path:
    """A trained model's folder: its parameters alone (``folder/best``, step 0, no optimiser)
    with ``config``, and ``files`` (name -> text, e.g. its JSON config), written beside
    ``folder`` and moved into place: never half written, and an older model there is replaced
    whole (orbax skips a step a folder already holds, so saving over it would keep the old
    parameters)."""
    folder = Path(folder)
    partial = folder.with_name(folder.name + ".partial")
    shutil.rmtree(partial, ignore_errors=True)
    state = TrainState(np.zeros((), np.int32), params, ())
    Checkpoints(partial).save_best(state, config, float(val_loss))
    for name, text in files.items():
        (partial / name).write_text(text)
    if folder.exists():
        shutil.rmtree(folder)
    partial.rename(folder)
    return folder
