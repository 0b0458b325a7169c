"""The names researchers already know (Stable-Baselines3, CleanRL, rl-zoo) and rlexp's key for each.

rlexp's config uses TorchRL's names (``clip_epsilon``, ``lmbda``, ``critic_coeff``). A key typed
from another library's vocabulary (``algorithm.clip_range=0.1``) gets, instead of a spelling guess
("did you mean algorithm.clip_value?": value clipping, the wrong knob), the key that means the same
thing here. The table is also docs/ppo.md's "Names from other libraries" (a test keeps them equal).
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Alias:
    """``name`` as ``where`` spell it is ``key`` in rlexp (``key`` None: no single key; ``note`` says
    what to use)."""

    name: str
    where: str  # the libraries that use the name
    key: str | None
    note: str = ""

    def hint(self) -> str:
        """``clip_range`` (Stable-Baselines3, rl-zoo) is `algorithm.clip_epsilon` here[; note]."""
        text = f"`{self.name}` ({self.where}) is "
        text += f"`{self.key}` here" if self.key else "not one key here"
        return text + (f": {self.note}" if self.note else "")


SB3 = "Stable-Baselines3, rl-zoo"
CLEANRL = "CleanRL"
ALL = "Stable-Baselines3, CleanRL, rl-zoo"

#: Every name, first the one the libraries share. A name in two libraries with two meanings
#: (``batch_size``) is one entry whose note says both.
ALIASES: tuple[Alias, ...] = (
    Alias("learning_rate", ALL, "algorithm.lr"),
    Alias("n_epochs", SB3, "algorithm.num_epochs"),
    Alias("update_epochs", CLEANRL, "algorithm.num_epochs"),
    Alias(
        "batch_size",
        ALL,
        "algorithm.mini_batch_size",
        "Stable-Baselines3's minibatch size; CleanRL's batch_size (num_envs x num_steps, the "
        "rollout) is trainer.frames_per_batch",
    ),
    Alias(
        "num_minibatches",
        CLEANRL,
        "algorithm.mini_batch_size",
        "set the minibatch size, trainer.frames_per_batch / num_minibatches",
    ),
    Alias(
        "n_steps",
        SB3,
        "trainer.frames_per_batch",
        "the rollout in env steps over all envs, n_steps x env.num_envs",
    ),
    Alias(
        "num_steps",
        CLEANRL,
        "trainer.frames_per_batch",
        "the rollout in env steps over all envs, num_steps x env.num_envs",
    ),
    Alias("n_envs", SB3, "env.num_envs"),
    Alias("num_envs", CLEANRL, "env.num_envs"),
    Alias("total_timesteps", f"{ALL} (n_timesteps)", "trainer.total_frames"),
    Alias("n_timesteps", SB3, "trainer.total_frames"),
    Alias("gae_lambda", ALL, "algorithm.lmbda"),
    Alias("clip_range", SB3, "algorithm.clip_epsilon"),
    Alias("clip_coef", CLEANRL, "algorithm.clip_epsilon"),
    Alias(
        "clip_range_vf",
        SB3,
        "algorithm.clip_value",
        "value clipping; note CleanRL clips the value with clip_coef when clip_vloss is set",
    ),
    Alias("clip_vloss", CLEANRL, "algorithm.clip_value", "a float here (the clip), not a switch"),
    Alias("ent_coef", ALL, "algorithm.entropy_coeff"),
    Alias("vf_coef", ALL, "algorithm.critic_coeff"),
    Alias("norm_adv", CLEANRL, "algorithm.normalize_advantage"),
    Alias(
        "target_kl",
        ALL,
        None,
        "their early stop of the epoch loop has no equivalent; algorithm.desired_kl adapts the "
        "learning rate to a KL target instead (rsl_rl)",
    ),
    Alias("log_std_init", SB3, "policy.init_log_std"),
    Alias("ortho_init", SB3, "policy.ortho_init"),
    Alias("net_arch", SB3, "policy.actor.hidden_sizes", "and policy.critic.hidden_sizes"),
    Alias("activation_fn", SB3, "policy.actor.activation", "and policy.critic.activation"),
    Alias(
        "features_extractor_class",
        SB3,
        "policy.encoder.name",
        "NatureCNN is nature (policy=cnn); the IMPALA ResNet is impala (docs/policies.md)",
    ),
    Alias("share_features_extractor", SB3, "policy.share_encoder"),
    Alias(
        "obs_groups",
        "rsl_rl",
        "policy.actor.observations",
        "and policy.critic.observations: lists of observation keys or groups (docs/policies.md)",
    ),
    Alias(
        "normalize",
        f"{SB3} (VecNormalize)",
        "env.normalize_observations",
        "and algorithm.normalize_rewards",
    ),
    Alias("max_episode_steps", "Gymnasium", "env.max_episode_steps"),
    Alias("env_id", CLEANRL, "env.name"),
)

_BY_NAME = {alias.name: alias for alias in ALIASES}


def alias_hint(key: str) -> str:
    """The hint for an unknown dotted ``key`` whose last part is another library's name (""
    when it is none, or when it is the name rlexp uses at that very place)."""
    name = key.rsplit(".", 1)[-1]
    alias = _BY_NAME.get(name)
    if alias is None or alias.key == key:
        return ""
    return alias.hint()
