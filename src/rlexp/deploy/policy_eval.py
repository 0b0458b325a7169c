"""``rlexp eval``: a checkpoint's policy, or an exported file's (``rlexp export``), on its run's own
env: deterministic episodes from the run's eval seed, and on request an mp4 of them.

A checkpoint is rebuilt from its own config and loaded as a resumed run would load it. An exported
file carries that config in its metadata JSON (``<file>.json``, docs/export.md), so both are
evaluated on the same env from the same seed and give the same numbers (tests/test_export.py).
The video is the ``record_video`` event's recorder (``rlexp.events.builtin.RecordVideo``) filming
env 0 of the eval env, with the camera of the run's own eval video when it had one.

Only the standard library is imported at module level: ``rlexp runs`` loads the cli, which names
``evaluate``, without loading torch.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

#: The ``schema`` value of an exported policy's metadata JSON.
EXPORT_SCHEMA = "rlexp-policy-export-v1"
#: Export format -> the file's suffix.
EXPORT_SUFFIXES = {"torchscript": ".pt", "onnx": ".onnx"}
#: Where ``rlexp eval --video`` looks for the run's own camera: its eval-video events.
_VIDEO_FUNCS = ("record_video", "rlexp.events.builtin.RecordVideo")


def metadata_path(path: str | Path) -> Path:
    """An exported file's metadata JSON: its own name plus ``.json`` (``policy.pt.json``)."""
    return Path(f"{path}.json")


def check_policy_finite(ckpt: dict[str, Any]) -> None:
    """NonFiniteError naming the policy tensors (normaliser statistics included) holding NaN/Inf."""
    import torch

    bad = [
        name
        for name, value in ckpt["policy"].items()
        if torch.is_tensor(value) and value.is_floating_point() and not torch.isfinite(value).all()
    ]
    if bad:
        from rlexp.algorithms.ppo import NonFiniteError

        shown = ", ".join(bad[:3]) + (f" and {len(bad) - 3} more" if len(bad) > 3 else "")
        raise NonFiniteError(
            f"checkpoint {ckpt['path']!r} holds non-finite policy weights ({shown}); there is "
            "nothing to evaluate: use an earlier checkpoint of the run"
        )


def eval_config(saved: dict, render: bool = False) -> dict:
    """The checkpoint's config, less what evaluation does not use and what may be checked
    differently here: its events (an older rlexp accepted other event params) and its thread count
    (the machine that trained may have had more CPUs). ``render``: Gymnasium copies render frames
    (``render_mode=rgb_array``; it changes no observation or reward)."""
    config = {**saved, "events": {"train": {}, "eval": {}}}
    config["trainer"] = {**(saved.get("trainer") or {}), "torch_threads": 1}
    if isinstance(saved.get("env"), dict):  # older checkpoints: a key that never did anything
        env = {k: v for k, v in saved["env"].items() if k != "vectorization"}
        if render and env.get("backend", "gymnasium") == "gymnasium":
            env["kwargs"] = {"render_mode": "rgb_array", **(env.get("kwargs") or {})}
        config["env"] = env
    return config


def typed_config(saved: dict, where: str, render: bool = False) -> Any:
    """``eval_config(saved)`` as the typed RootConfig; ``ValueError`` naming ``where`` (the file the
    config came from) and the key when the stored config does not validate: a file is data, and an
    unknown key or a wrong type in it is one line, never a traceback."""
    from rlexp.config.validate import to_root_config

    try:
        return to_root_config(eval_config(saved, render=render))
    except Exception as exc:  # ConfigError, and OmegaConf's own (ConfigKeyError, ValidationError)
        key = getattr(exc, "full_key", None)
        text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise ValueError(
            f"{where} holds a config rlexp cannot use ({f'{key}: ' if key else ''}{text})"
        ) from None


PolicyBuilder = Callable[[Any, Any], Callable[[Any], Any]]


@dataclass
class EvalSource:
    """What ``rlexp eval`` evaluates: the file, the run config it came from, and how to make its
    deterministic policy (``build(config, env)``: a tensordict -> tensordict with ``action``)."""

    path: str
    kind: str  # checkpoint | torchscript | onnx
    global_step: int
    config: dict[str, Any]
    build: PolicyBuilder
    checkpoint: str | None = None  # an exported file's source checkpoint
    chosen: str = "as given"  # why this checkpoint (rlexp.checkpoints.files.select_checkpoint)


def open_source(path: str | Path, which: str | None = None) -> EvalSource:
    """A checkpoint (a file, or the one of a run dir that ``which`` picks: the rule of
    ``rlexp.checkpoints.files.select_checkpoint``, shared with ``rlexp export``) or an exported file (a
    ``.onnx``, or a file with its export metadata JSON beside it)."""
    from rlexp.checkpoints.files import select_checkpoint

    # torch warns about the pickle protocol of a file it is about to refuse: noise next to the error
    warnings.filterwarnings("ignore", "Detected pickle protocol", UserWarning)
    p = Path(path)
    if p.suffix == ".onnx" or metadata_path(p).is_file():
        if which is not None:
            raise ValueError(
                f"--checkpoint {which}: {str(p)!r} is an exported policy, not a run dir"
            )
        return _exported_source(p)
    if p.is_file() and _is_torchscript(p):
        raise ValueError(
            f"{str(p)!r} is a TorchScript file without its export metadata "
            f"{metadata_path(p).name!r} beside it (rlexp export writes both): nothing says which "
            "env it acts in"
        )
    ckpt, chosen = select_checkpoint(p, which)  # before the heavy imports: a bad path fails fast
    check_policy_finite(ckpt)
    return EvalSource(
        ckpt["path"],
        "checkpoint",
        int(ckpt["global_step"]),
        ckpt["config"],
        _from_ckpt(ckpt),
        chosen=chosen,
    )


def _is_torchscript(path: Path) -> bool:
    import zipfile

    try:
        with zipfile.ZipFile(path) as archive:
            return any(n.endswith("/constants.pkl") for n in archive.namelist())
    except (OSError, zipfile.BadZipFile):
        return False


def _from_ckpt(ckpt: dict[str, Any]) -> PolicyBuilder:
    def build(config: Any, env: Any) -> Callable[[Any], Any]:
        from rlexp.checkpoints.files import check_checkpoint_fits, check_policy_before_building
        from rlexp.envs.layout_check import check_layout
        from rlexp.policies.actor_critic import policy_for_env

        check_layout(ckpt.get("observation_layout"), env, f"checkpoint {ckpt.get('path')!r}")
        check_policy_before_building(ckpt, lambda: policy_for_env(config.policy, config.env, env))
        policy = policy_for_env(config.policy, config.env, env)
        check_checkpoint_fits(
            ckpt, config, policy
        )  # loads the weights; ValueError if they do not fit
        from rlexp.training.evaluation import acting_policy

        # on the env's device: a batched torch env on a GPU is evaluated without copies per step
        # (a recurrent policy: its state carried across steps, reset per episode)
        return acting_policy(policy.to(env.device or "cpu"))

    return build


def read_metadata(path: Path) -> dict[str, Any]:
    """An exported file's metadata; ValueError / FileNotFoundError naming the file that is wrong."""
    meta_file = metadata_path(path)
    if not path.is_file():
        raise FileNotFoundError(f"exported policy {str(path)!r} does not exist")
    if not meta_file.is_file():
        raise FileNotFoundError(
            f"exported policy {str(path)!r} has no metadata {meta_file.name!r} beside it "
            "(rlexp export writes both; it names the env and config to evaluate on)"
        )
    try:
        meta = json.loads(meta_file.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"export metadata {str(meta_file)!r} is unreadable: {exc}") from None
    if not isinstance(meta, dict) or meta.get("schema") != EXPORT_SCHEMA:
        raise ValueError(f"{str(meta_file)!r} is not rlexp export metadata ({EXPORT_SCHEMA!r})")
    if meta.get("format") not in EXPORT_SUFFIXES or not isinstance(meta.get("config"), dict):
        raise ValueError(f"export metadata {str(meta_file)!r} lacks a valid 'format' or 'config'")
    from rlexp.deploy.export_meta import check_fields

    check_fields(meta, f"export metadata {str(meta_file)!r}")
    return meta


def _exported_source(path: Path) -> EvalSource:
    meta = read_metadata(path)

    def build(config: Any, env: Any) -> Callable[[Any], Any]:
        from rlexp.deploy.export_feed import ExportedPolicy, actor_feed, env_actions
        from rlexp.deploy.export_meta import check_action_space

        where = f"exported policy {str(path)!r}"
        # the actor's inputs gathered from the env's observation (the critic's are never read)
        feed = actor_feed(meta, env, where)
        check_action_space(meta, env, where)
        # (a recurrent policy's file also takes and returns its state: carried, reset per episode)
        return ExportedPolicy(
            load_exported(path, meta), feed, env_actions(meta), meta.get("memory")
        )

    return EvalSource(
        str(path), meta["format"], int(meta["global_step"]), meta["config"], build,
        checkpoint=meta.get("source_checkpoint"),
    )  # fmt: skip


def load_exported(path: Path, meta: dict[str, Any]) -> Callable[[Any], Any]:
    """The exported file as a function of its inputs (``meta["inputs"]``' order, then a recurrent
    policy's state inputs, ``meta["memory"]["state"]``; older exports: ``obs [batch, obs_dim]
    float32``) -> the action, or (recurrent) the tuple of the action and the new state (tensors)."""
    import torch

    names = [i["name"] for i in meta.get("inputs") or [{"name": meta.get("input_name")}]]
    outs = [meta.get("output_name")]
    memory = meta.get("memory")
    if memory is not None:  # the state in after the observation, out after the action
        names += [s["name"] for s in memory["state"]]
        outs += [s["output"] for s in memory["state"]]
    if meta["format"] == "torchscript":
        try:
            module = torch.jit.load(str(path), map_location="cpu").eval()
        except (RuntimeError, ValueError) as exc:
            raise ValueError(f"exported policy {str(path)!r} does not load: {exc}") from None
        takes = [a.name for a in module.forward.schema.arguments][1:]  # (after self)
        if meta.get("inputs") is not None:  # (older exports named no inputs)
            _check_signature(path, takes, names)
        return module
    from rlexp.extras import require

    require("export", "rlexp eval of an ONNX file", ("onnxruntime",))
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads = 1  # as torch in evaluation: one thread
    try:
        session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    except Exception as exc:  # onnxruntime's own exception types (InvalidProtobuf, ...)
        text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise ValueError(f"exported policy {str(path)!r} does not load: {text}") from None
    _check_signature(path, [i.name for i in session.get_inputs()], names)

    def act(*inputs: Any) -> Any:
        feed = {n: x.numpy() for n, x in zip(names, inputs, strict=True)}
        got = [torch.from_numpy(y) for y in session.run(outs, feed)]
        return got[0] if memory is None else tuple(got)

    return act


def _check_signature(path: Path, takes: list[str], names: list[str]) -> None:
    """One line when the file's inputs are not the ones its metadata names (a recurrent policy's
    state among them): the metadata is another file's, or was edited."""
    if takes != names:
        raise ValueError(
            f"exported policy {str(path)!r} takes the inputs {takes}; its metadata names {names}: "
            "they belong together (re-export the checkpoint with rlexp export)"
        )


def evaluate(
    checkpoint: str,
    episodes: int | None,
    num_envs: int | None,
    seed: int | None = None,
    video: str | Path | None = None,
    which: str | None = None,
) -> dict[str, Any]:
    """Rebuild the run's env and the policy of a checkpoint (a file, or the one of a run dir that
    ``which`` picks: ``select_checkpoint``) or of an exported file, and evaluate it
    deterministically; ``video``: also write an mp4 of env 0's episodes there ("": beside the
    evaluated file). ``episodes`` None: the run's own ``trainer.eval_episodes``; with the run's
    seed and env count, the episodes of its eval rounds, number for number."""
    if episodes is not None and episodes < 1:
        raise ValueError(f"episodes={episodes}; evaluate at least 1 episode")
    if num_envs is not None and num_envs < 1:
        raise ValueError(f"num_envs={num_envs}; use at least 1 env (None: the run's num_eval_envs)")
    source = open_source(checkpoint, which)
    if video == "":  # --video without a path: beside the evaluated file, <stem>.mp4
        video = Path(source.path).with_suffix(".mp4")

    from rlexp.envs.factory import make_env
    from rlexp.training.build import seed_everything  # not rlexp.app: that imports Hydra (~0.2 s)
    from rlexp.training.evaluation import run_episodes
    from rlexp.training.loop import one_torch_thread

    what = "checkpoint" if source.kind == "checkpoint" else "exported policy"
    from rlexp.runtime.env_source import ensure_env_importable, env_name_in, run_dir_of

    # The user's own run may name the folder its env module came from; an exported file never does.
    run_dir = run_dir_of(source.path) if source.kind == "checkpoint" else None
    ensure_env_importable(env_name_in(source.config), run_dir)
    if video is not None:
        _check_renders(source.config)
    config = typed_config(source.config, f"{what} {source.path!r}", render=video is not None)
    e = config.env
    if source.kind != "checkpoint":  # a shared file's metadata is data: it imports nothing
        from rlexp.deploy.export_meta import check_env_names

        check_env_names(e, f"exported policy {source.path!r}")
    if episodes is None:
        episodes = max(1, config.trainer.eval_episodes)
    if seed is None:  # the run's own eval seed: the same episodes as the Trainer's eval rounds
        from rlexp.training.build import EVAL_SEED_OFFSET

        seed = config.seed + EVAL_SEED_OFFSET
    seed_everything(seed)
    try:
        env = make_env(e, num_envs or max(1, e.num_eval_envs), seed)
    except KeyError as exc:  # check_gym_id: the id, or its module's own failure, in one line
        raise ValueError(exc.args[0] if exc.args else str(exc)) from None
    except TypeError as exc:  # the constructor refused a kwarg (--video's render_mode included)
        extra = " with render_mode='rgb_array' (--video)" if video is not None else ""
        raise ValueError(f"env.name={e.name!r} cannot be built{extra}: {exc}") from None
    try:
        policy = source.build(config, env)
        film = None if video is None else _Video(env, source, Path(video))
        if film is not None:
            env.set_seed(seed)  # the camera check reset the env: start from the eval seed again
        with one_torch_thread():  # as the run's eval rounds: the same kernels, the same numbers
            metrics = run_episodes(env, policy, episodes, None if film is None else film.on_step)
        written = None if film is None else film.write()
    finally:
        env.close()
    return {
        "path": source.path,
        "kind": source.kind,
        "checkpoint": source.checkpoint,
        "chosen": source.chosen,
        "global_step": source.global_step,
        "mean_return": metrics["eval/episode_return"],
        "std_return": metrics["eval/episode_return_std"],
        "episodes": int(metrics["eval/episodes"]),
        "video": None if written is None else str(written),
    }


def _check_renders(saved: dict[str, Any]) -> None:
    """``--video`` on a Gymnasium env whose constructor takes no ``render_mode``: one line now
    (``rlexp eval`` would pass it ``render_mode='rgb_array'``), not the constructor's TypeError."""
    env = saved.get("env") if isinstance(saved.get("env"), dict) else {}
    if env.get("backend", "gymnasium") not in ("gymnasium", "gymnasium_async"):
        return
    if "render_mode" in (env.get("kwargs") or {}):  # the run's own choice: as the run built it
        return
    from rlexp.envs.gym_ids import render_refusal

    refusal = render_refusal(str(env.get("name")), "--video")
    if refusal is not None:
        raise ValueError(refusal)


class _Video:
    """``rlexp eval --video``: env 0's frames through the record_video event's recorder, one mp4."""

    def __init__(self, env: Any, source: EvalSource, out: Path) -> None:
        from rlexp.events.builtin import RecordVideo
        from rlexp.events.manager import EventContext
        from rlexp.events.video import VIDEO_DEFAULTS, check_video_env

        where = "rlexp eval --video"
        if out.suffix != ".mp4":
            raise ValueError(f"--video {str(out)!r}: give a file name ending in .mp4")
        if not out.parent.is_dir():
            raise FileNotFoundError(f"--video {str(out)!r}: folder {str(out.parent)!r} is missing")
        _check_writable(out)
        self.params = {**VIDEO_DEFAULTS, **_run_camera(source.config), "env_id": 0}
        try:  # (quiet: Gymnasium's own camera and frame size are no news to an eval)
            with quiet("rlexp.events"):
                check_video_env(env, where, None, **self.params)
        except TypeError as exc:  # an env that cannot render (env.backend=torchrl_gym)
            raise ValueError(str(exc)) from None
        self.out = out
        self.recorder = RecordVideo()
        self.ctx = EventContext(env=env, global_step=source.global_step, event=where)

    def on_step(self, td: Any) -> None:
        self.recorder(self.ctx, **self.params)

    def write(self) -> Path:
        """The mp4, written by the recorder in a temporary folder beside ``out``, then renamed."""
        import tempfile

        tmp = Path(tempfile.mkdtemp(prefix=".rlexp-video-", dir=self.out.parent))
        try:
            params = {**self.params, "name": "eval", "save_path": str(tmp.resolve())}
            with quiet("rlexp.events"):  # its log line names the temporary file
                self.recorder.finalize(self.ctx, **params, allow_outside_run_dir=True)
            if self.recorder.failed is not None:  # e.g. a full disk: one line, exit 2
                raise OSError(f"--video {str(self.out)!r} not written: {self.recorder.failed}")
            os.replace(self.recorder.written[-1], self.out)
        finally:
            for leftover in tmp.iterdir():
                leftover.unlink()
            tmp.rmdir()
        return self.out


def _check_writable(out: Path) -> None:
    """``--video`` into a folder that cannot be written: one line before the episodes, not an
    ``OSError`` after them."""
    from rlexp.run.writable import probe_dir
    from rlexp.runtime.entry import os_error_line

    longest = len(f".rlexp-video-xxxxxxxx/.eval_step_000000000.tmp-{os.getpid()}.mp4")
    try:
        probe_dir(out.parent, longest)
    except OSError as exc:
        raise ValueError(f"--video {str(out)!r} cannot be written: {os_error_line(exc)}") from None


def _run_camera(saved: dict[str, Any]) -> dict[str, Any]:
    """The camera (resolution, eye, target, ..., fps) of the run's eval video event, if any."""
    events = ((saved.get("events") or {}).get("eval")) or {}
    for event in events.values():
        if isinstance(event, dict) and event.get("func") in _VIDEO_FUNCS:
            params = dict(event.get("params") or {})
            for key in ("signal", "name", "save_path", "allow_outside_run_dir", "env_id"):
                params.pop(key, None)
            return params
    return {}


@contextlib.contextmanager
def quiet(name: str) -> Iterator[None]:
    """``name``'s INFO and WARNING lines off for a moment (errors still show)."""
    logger = logging.getLogger(name)
    level = logger.level
    logger.setLevel(logging.ERROR)
    try:
        yield
    finally:
        logger.setLevel(level)
