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

        from rlexp.registry import check_module_name

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
