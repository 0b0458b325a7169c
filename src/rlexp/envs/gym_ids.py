"""Gymnasium ids and building, shared by the in-process adapter and the gymnasium_async workers
(no torch here: a worker process imports this): the registered names with close matches for a bad
one, and MuJoCo's build warnings routed to the log.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator

import gymnasium as gym

log = logging.getLogger(__name__)

#: The Gymnasium MuJoCo suite (any other registered id works too; these are the tested ones).
GYM_MUJOCO_TASKS = (
    "HalfCheetah-v5",
    "Hopper-v5",
    "Walker2d-v5",
    "Ant-v5",
    "InvertedPendulum-v5",
    "InvertedDoublePendulum-v5",
    "Humanoid-v5",
    "Swimmer-v5",
    "Reacher-v5",
)


def check_gym_id(env_id: str) -> None:
    """Raise a KeyError naming close matches when ``env_id`` is not a registered Gymnasium id.

    ``module:EnvId`` (Gymnasium's own syntax) imports ``module`` first, so that the package that
    registers ``EnvId`` does so; ids registered by an ``rlexp.plugins`` entry point are in the
    registry once the plugins are loaded (``rlexp train`` loads them at start-up)."""
    module, name = "", env_id
    if ":" in env_id:
        module, name = env_id.split(":", 1)
        import importlib

        from rlexp.common.registry import check_module_name

        try:  # before importing: no private part, no standard-library module ("this", "os")
            check_module_name(module, f"env.name={env_id!r}", None)
        except ValueError as exc:
            raise KeyError(str(exc)) from None

        try:
            importlib.import_module(module)
        except Exception as exc:  # ModuleNotFoundError, or the module's own failure
            from rlexp.config.rules import first_line

            raise KeyError(
                f"env.name={env_id!r}: module {module!r} could not be imported "
                f"({type(exc).__name__}: {first_line(exc)}); "
                "install the package that registers the env (pip install -e PATH)"
            ) from None
    if name in gym.registry:
        return
    import difflib

    close = difflib.get_close_matches(name, list(gym.registry), n=3)
    hint = f"; did you mean {close[0]!r}?" if close else ""
    where = f" (module {module!r} was imported but did not register it)" if name != env_id else ""
    raise KeyError(
        f"env.name={env_id!r} is not a registered Gymnasium environment{where}; "
        f"MuJoCo tasks: {list(GYM_MUJOCO_TASKS)}{hint}; your own env: docs/envs.md"
    )


#: ``gymnasium.make``'s own keyword arguments (besides the constructor's).
MAKE_KWARGS = ("max_episode_steps", "disable_env_checker")


def constructor_args(env_id: str, complete: bool = True) -> list[str] | None:
    """The keyword arguments a registered env's constructor takes (``env.kwargs``), read from its
    signature; None when it cannot be told (an entry point that does not load; with ``complete``,
    also a constructor that takes ``**kwargs``: its named arguments are not all it takes)."""
    import inspect

    try:
        check_gym_id(env_id)  # (imports the module of module:EnvId, which registers the id)
        spec = gym.spec(env_id.split(":", 1)[-1])
        creator = spec.entry_point
        if isinstance(creator, str):
            from gymnasium.envs.registration import load_env_creator

            creator = load_env_creator(creator)
        params = inspect.signature(creator).parameters.values()
    except Exception:  # an unregistered id, a broken entry point, a builtin without a signature
        return None
    if complete and any(p.kind is p.VAR_KEYWORD for p in params):
        return None
    kinds = (inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY)
    return [p.name for p in params if p.kind in kinds and p.name != "self"]


def kwarg_hint(env_id: str, bad: str) -> str:
    """``; did you mean 'x'?`` (and what the constructor takes) for an ``env.kwargs`` key the env
    refused; "" when its signature cannot be read."""
    import difflib

    named = constructor_args(env_id, complete=False)
    if named is None:
        return ""
    close = difflib.get_close_matches(bad, [*named, *MAKE_KWARGS], n=1, cutoff=0.6)
    hint = f"; did you mean {close[0]!r}?" if close else ""
    if constructor_args(env_id) is None:  # it takes **kwargs too: its named ones are not all
        return hint
    return hint + f" (its constructor takes: {', '.join(named) or 'no arguments'})"


def render_refusal(env_id: str, where: str) -> str | None:
    """One line for an env whose constructor takes no ``render_mode`` (it cannot give rlexp the
    rgb_array frames a video needs), naming ``where`` the video was asked for; None otherwise."""
    args = constructor_args(env_id)
    if args is None or "render_mode" in args:
        return None
    return (
        f"{where}: env.name={env_id!r} cannot render: its constructor takes no render_mode "
        f"(it takes: {', '.join(args) or 'no arguments'}); give it a render_mode='rgb_array' "
        "argument that returns frames from render(), or record no video"
    )


#: MuJoCo warnings about Gymnasium's own model files, not the user's: MuJoCo 4.0 deprecates the
#: ``settotalmass`` compiler attribute that gymnasium's HalfCheetah, Hopper, Walker2d... XML use.
IGNORED_MUJOCO_WARNINGS = ("compiler attribute 'settotalmass' is deprecated",)


@contextlib.contextmanager
def mujoco_build_warnings(env_id: str) -> Iterator[None]:
    """While Gymnasium compiles ``env_id``'s MuJoCo models: MuJoCo's warnings go to this module's
    logger instead of stdout and a ``MUJOCO_LOG.TXT`` in the working directory, and the deprecation
    of Gymnasium's own XML (twice per env copy, 22 lines per HalfCheetah run) is dropped. A handler
    someone else installed is left alone; stepping keeps MuJoCo's own handler."""
    try:
        entry = str(getattr(gym.spec(env_id), "entry_point", ""))
    except Exception:  # checked (and reported) by check_gym_id
        entry = ""
    if "mujoco" not in entry:  # a Gymnasium task that is not MuJoCo's: MuJoCo is not imported
        yield
        return
    import mujoco

    if mujoco.get_mju_user_warning() is not None:
        yield
        return

    def forward(message: str) -> None:
        if not message.startswith(IGNORED_MUJOCO_WARNINGS):
            log.warning("[mujoco] %s", message)

    mujoco.set_mju_user_warning(forward)
    try:
        yield
    finally:
        mujoco.set_mju_user_warning(None)
