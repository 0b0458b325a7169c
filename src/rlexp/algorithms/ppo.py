"""PPO: TorchRL's ``GAE`` and ``ClipPPOLoss``, Adam, epochs x minibatches, optional LR annealing.

Options, all off by default (docs/ppo.md): reward scaling by the running std of the discounted
return (``normalize_rewards``, ``normalize.py``) and reward clipping (``clip_rewards``), both applied
to the rollout before GAE; rsl_rl's adaptive learning rate (``desired_kl``), adjusted before every
minibatch step from the KL between the behaviour and the current policy (Gaussian or categorical).

Speed (docs/performance.md): the loss can run through ``torch.compile`` (``algorithm.compile``), Adam
is the fused kernel where torch has one, and the per-minibatch statistics stay tensors until the end
of the update. The minibatch step is ``fused_step.py`` (ClipPPOLoss's maths on plain tensors,
backward, clipping and Adam; compiled with the loss's decision) wherever it covers the run, today's
path (ClipPPOLoss, then ``guarded_step``) otherwise, chosen once at the first update and logged.
None of it changes the maths: ``tests/test_ppo_math.py`` checks a whole update against a plain-torch
PPO, ``tests/test_fast_update.py`` the fused step against ClipPPOLoss. The guarded optimiser step
(gradient sync, NaN guard, clipping) and Adam are shared with GRPO (``base.py``).
"""

from __future__ import annotations

import dataclasses
import logging
import os
import shutil
import time
from collections.abc import Callable

import torch
from tensordict import TensorDictBase
from torchrl.objectives import ClipPPOLoss
from torchrl.objectives.value import GAE

from rlexp.algorithms import make_algorithm
from rlexp.algorithms.base import (
    AUTO_COMPILE_MIN_SAVING_S,
    COMPILE_CHOICES,
    COMPILE_SAVING_PER_SAMPLE_S,
    COMPILE_SAVING_PER_UPDATE_S,
    FUSED_COMPILE_SAVING_PER_UPDATE_S,
    GradSync,
    MutableHyperparameters,
    NonFiniteError,
    compile_saving_s,
    make_optimizer,
    parse_compile,
)
from rlexp.algorithms.fused_step import MINIBATCH_KEYS, FusedPPOStep
from rlexp.algorithms.fused_step import unsupported as fused_unsupported
from rlexp.algorithms.normalize import ReduceSum, RewardNormalizer
from rlexp.common.observations import in_chunks, next_is_following, structured
from rlexp.config.schema import AlgorithmConfig
from rlexp.config.validate import ConfigError
from rlexp.policies.actor_critic import POLICIES, ActorCritic
from rlexp.policies.encoders import channels_last_images
from rlexp.policies.heads import gaussian_kl

# NonFiniteError, make_optimizer, parse_compile, COMPILE_CHOICES, the compile=auto constants
# (rlexp.algorithms.base) and make_algorithm (rlexp.algorithms) are importable from here too.
__all__ = [
    "AUTO_COMPILE_MIN_SAVING_S",
    "COMPILE_CHOICES",
    "COMPILE_SAVING_PER_SAMPLE_S",
    "COMPILE_SAVING_PER_UPDATE_S",
    "FUSED_COMPILE_SAVING_PER_UPDATE_S",
    "LOSS_KEYS",
    "PPO",
    "STAT_KEYS",
    "NonFiniteError",
    "adaptive_learning_rate",
    "compile_unavailable",
    "gaussian_kl",
    "make_algorithm",
    "make_gae",
    "make_optimizer",
    "parse_compile",
]

log = logging.getLogger(__name__)

LOSS_KEYS = ("loss_objective", "loss_critic", "loss_entropy")
STAT_KEYS = (*LOSS_KEYS, "entropy", "grad_norm", "clip_fraction", "kl_approx")
#: rsl_rl's adaptive schedule (``algorithm.desired_kl``): the factor and the learning rate's bounds.
ADAPTIVE_LR_FACTOR = 1.5
ADAPTIVE_LR_MIN = 1e-5
ADAPTIVE_LR_MAX = 1e-2
#: Where the behaviour policy's distribution rides in the flattened rollout (renamed from ``loc`` /
#: ``scale`` or ``logits``, so that the loss's actor, which writes those keys, never meets them).
BEHAVIOUR_PREFIX = "behaviour_"


def make_gae(cfg: AlgorithmConfig, value_network=None) -> GAE:
    """TorchRL's GAE: bootstraps from V(next obs) unless ``terminated``; ``done`` cuts the trace.

    With ``value_network=None`` it reads ``state_value`` and ``("next", "state_value")`` from the
    batch (``PPO.compute_advantages`` fills them). TorchRL's vectorised recursion: 0.55 ms for a
    2048-step rollout of one env against 12 ms for its step-by-step loop (its default), within 1e-5."""
    return GAE(
        gamma=cfg.gamma,
        lmbda=cfg.lmbda,
        value_network=value_network,
        average_gae=False,
        differentiable=False,
        vectorized=True,
    )


def adaptive_learning_rate(lr: float, kl: float, desired_kl: float) -> float:
    """rsl_rl's ``schedule="adaptive"``: divide by 1.5 (not below 1e-5) when ``kl`` is above twice
    the target, multiply by 1.5 (not above 1e-2) when it is below half of it (and above 0)."""
    if kl > 2.0 * desired_kl:
        return max(ADAPTIVE_LR_MIN, lr / ADAPTIVE_LR_FACTOR)
    if 0.0 < kl < desired_kl / 2.0:
        return min(ADAPTIVE_LR_MAX, lr * ADAPTIVE_LR_FACTOR)
    return lr


class PPO(MutableHyperparameters):
    """One PPO learner: ``update(batch)`` runs GAE then the clipped-surrogate epochs on a rollout."""

    #: Whether the first update may choose the fused minibatch step (fused_step.py) over today's.
    use_fused_step: bool = True
    rollout_values: bool = True  #: GAE takes V(s_t) from the rollout where collection wrote it

    def __init__(
        self,
        cfg: AlgorithmConfig,
        policy: ActorCritic,
        total_iterations: int,
        nan_guard: bool = True,
        grad_sync: GradSync | None = None,
        reduce_sum: ReduceSum | None = None,
    ) -> None:
        """``grad_sync`` (distributed): averages gradients over ranks; ``reduce_sum`` sums the
        reward normaliser's statistics over ranks, the process group's sum when left out and
        ``grad_sync`` is given (the builder passes ``grad_sync`` exactly when distributed)."""
        if cfg.name != "ppo":
            raise ValueError(f"algorithm.name={cfg.name!r}; available: ['ppo']")
        if getattr(policy, "critic", None) is None:
            name = next(
                (n for n, c in POLICIES.items() if type(policy) is c), type(policy).__name__
            )
            raise ValueError(
                f"algorithm=ppo needs a critic: policy=actor_critic (policy.name={name} has none)"
            )
        if cfg.loss_critic_type not in ("l1", "l2", "smooth_l1"):
            raise ValueError(
                f"algorithm.loss_critic_type={cfg.loss_critic_type!r}; choose from ['l1', 'l2', 'smooth_l1']"
            )
        if cfg.desired_kl is not None and cfg.anneal_lr:
            raise ValueError(
                f"algorithm.desired_kl={cfg.desired_kl} and algorithm.anneal_lr=true both set the "
                "learning rate; use one (algorithm.anneal_lr=false or algorithm.desired_kl=null)"
            )
        self.cfg = dataclasses.replace(cfg)  # its own copy: hooks may change its values
        self.policy = policy
        self.total_iterations = max(1, total_iterations)
        self.nan_guard = nan_guard
        self.grad_sync = grad_sync  # distributed: averages gradients over ranks after backward
        self.gae = make_gae(cfg)  # values come from compute_advantages
        self.loss = ClipPPOLoss(
            actor_network=policy.actor,
            critic_network=policy.critic,
            clip_epsilon=cfg.clip_epsilon,
            # Always: TorchRL then reports the policy's entropy, logged whatever the coefficient;
            # the term joins the total loss only while entropy_coeff != 0 (``_total``).
            entropy_bonus=True,
            entropy_coeff=cfg.entropy_coeff,
            critic_coeff=cfg.critic_coeff,
            loss_critic_type=cfg.loss_critic_type,
            normalize_advantage=cfg.normalize_advantage,
            clip_value=cfg.clip_value,
            functional=False,
            log_explained_variance=False,  # not logged: two variances per minibatch saved
        )
        self.loss.set_keys(sample_log_prob="action_log_prob")
        named = [(n, p) for n, p in policy.named_parameters() if p.requires_grad]
        self.param_names = [n for n, _ in named]  # for NaN-guard messages
        self.params = [p for _, p in named]
        self.optimizer = make_optimizer(self.params, cfg)
        self.compile = parse_compile(cfg.compile)
        if self.compile == "true":  # fail at build time, naming the key, not at the first update
            problem = compile_unavailable(self.params[0].device if self.params else None)
            if problem is not None:
                raise ConfigError(
                    f"algorithm.compile=true, but torch.compile cannot run here: {problem}; "
                    "use algorithm.compile=auto or false"
                )
        self._loss_fn: Callable[[TensorDictBase], TensorDictBase] = self.loss
        self._compile_decided = False
        self.compiled = False  # whether the loss runs through torch.compile
        # The fused minibatch step (fused_step.py), chosen with the compile decision at the first
        # update where it covers this run's settings; None: today's path (ClipPPOLoss).
        self.fused: FusedPPOStep | None = None
        self._shuffle = torch.Generator()  # minibatch order (CPU: randperm indexes a CPU batch)
        self.iteration = 0
        self.reset_each_rollout = False  # GAE bootstraps across rollouts: episodes run on
        # Reward scaling: statistics of this learner's (and, distributed, all ranks') returns.
        self.reward_normalizer = RewardNormalizer(cfg.gamma) if cfg.normalize_rewards else None
        if reduce_sum is None and grad_sync is not None:
            from rlexp.runtime.distributed import all_reduce_sum

            reduce_sum = all_reduce_sum
        self.reduce_sum = reduce_sum

    @torch.no_grad()
    def compute_advantages(self, batch: TensorDictBase) -> TensorDictBase:
        """Writes ``state_value``, ``("next", "state_value")``, ``advantage`` and ``value_target``
        (time is the last batch dim) with TorchRL's GAE.

        The values are computed here, not by GAE's value network: V(s_t) in one pass over the
        rollout (or the rollout's own, where an image policy's collection wrote them with these
        parameters: ``Policy.sampling_policy(values=True)``), and V(s'_t) reused from V(s_t+1)
        wherever the next observation *is* the following step's observation (bit-equal: no reset
        in between), so the critic runs again only on the final observations of finished episodes
        and on the last step: same values as TorchRL's V(s) and V(s') apart. A TensorDict
        observation is compared entry by entry; the critic reads images in minibatch chunks."""
        obs = batch.get("observation")
        next_obs = batch.get(("next", "observation"))
        critic = self.policy.critic_net
        if structured(obs):
            critic = in_chunks(critic, self.cfg.mini_batch_size)
        value = batch.get("state_value", None)  # [*B, T, 1]
        value = critic(obs) if value is None else value
        follows = next_is_following(obs, next_obs, batch.batch_dims)  # [*B, T-1]
        own = torch.cat([~follows, follows.new_ones(follows.shape[:-1] + (1,))], dim=-1)
        next_value = torch.empty_like(value)
        next_value[..., :-1, :] = value[..., 1:, :]
        next_value[own] = critic(next_obs[own])
        batch.set("state_value", value)
        batch.set(("next", "state_value"), next_value)
        return self.gae(batch)

    def scale_rewards(self, batch: TensorDictBase) -> TensorDictBase:
        """The rollout with ``("next", "reward")`` normalised and/or clipped, as a shallow copy: the
        caller's batch keeps the env's rewards (episode statistics, events)."""
        reward = batch.get(("next", "reward"))
        if self.reward_normalizer is not None:
            reward = self.reward_normalizer.scale(
                reward, batch.get(("next", "done")), self.reduce_sum
            )
        if self.cfg.clip_rewards is not None:
            reward = reward.clamp(-self.cfg.clip_rewards, self.cfg.clip_rewards)
        scaled = batch.copy()
        scaled.set(("next", "reward"), reward)
        return scaled

    def update(self, batch: TensorDictBase) -> dict[str, float]:
        """GAE over the rollout, then ``num_epochs`` passes of shuffled minibatches."""
        lr = self.learning_rate()
        self._set_lr(lr)
        if self.reward_normalizer is not None or self.cfg.clip_rewards is not None:
            batch = self.scale_rewards(batch)
        self.compute_advantages(batch)
        adaptive = self.cfg.desired_kl is not None
        dist_keys = self.policy.actor_net.dist_keys  # loc, scale (Gaussian) or logits
        flat = batch.reshape(-1).select(
            *MINIBATCH_KEYS,
            *(dist_keys if adaptive else ()),
            strict=False,
        )
        flat = channels_last_images(flat)  # the encoders' layout once, not per minibatch
        if adaptive:
            missing = [k for k in dist_keys if k not in flat.keys()]
            if missing:
                raise KeyError(
                    f"algorithm.desired_kl needs the behaviour policy's {missing} in the rollout "
                    "(the sampling policy writes them)"
                )
            for key in dist_keys:
                flat.rename_key_(key, BEHAVIOUR_PREFIX + key)
        n = flat.shape[0]
        mb = min(self.cfg.mini_batch_size, n)
        if not self._compile_decided:
            self._decide_compile(
                updates=self.total_iterations * self.cfg.num_epochs * (n // mb), mb=mb
            )
            self._decide_fused()
        # Minibatch order from a generator of its own, seeded from the global RNG once per update:
        # whatever the loss draws (TorchRL's compiled entropy draws a sample) cannot change it.
        self._shuffle.manual_seed(int(torch.randint(2**62, (1,)).item()))
        if self.fused is not None:
            rows, keys = self.fused.epochs(flat, self.cfg, mb, self._shuffle), list(STAT_KEYS)
        else:
            rows, keys = self._epochs(flat, mb, adaptive)
        self.iteration += 1
        if not rows:  # fewer samples than one minibatch: nothing was computed, nothing to log
            return {"loss/learning_rate": lr}
        # Only what the loss computed is logged: a missing statistic is absent, never 0.
        metrics = dict(zip(keys, torch.stack(rows).mean(0).tolist(), strict=True))
        out = {
            "loss/policy": metrics["loss_objective"],
            "loss/value": metrics["loss_critic"],
            "loss/entropy": metrics["entropy"],  # the policy's mean entropy (TorchRL's "entropy")
            "loss/grad_norm": metrics["grad_norm"],
            **{
                name: metrics[key]
                for name, key in (
                    ("loss/clip_fraction", "clip_fraction"),
                    ("loss/approx_kl", "kl_approx"),
                )
                if key in metrics
            },
            # adaptive: the rate the last step took and the next update starts from (as rsl_rl logs)
            "loss/learning_rate": self.cfg.lr if adaptive else lr,
            **self.policy.metrics(),  # loss/log_std for a Gaussian policy
        }
        if self.cfg.entropy_coeff != 0.0:  # the entropy term of the loss: -entropy_coeff * entropy
            out["loss/entropy_term"] = metrics["loss_entropy"]
        if self.reward_normalizer is not None:
            out["loss/reward_std"] = self.reward_normalizer.std()
        return out

    def _epochs(
        self, flat: TensorDictBase, mb: int, adaptive: bool
    ) -> tuple[list[torch.Tensor], list[str]]:
        """Today's minibatch step: TorchRL's ClipPPOLoss on TensorDict slices, then
        ``guarded_step``; per minibatch a row of the statistics named by the returned keys."""
        n = flat.shape[0]
        rows: list[torch.Tensor] = []  # per minibatch: the STAT_KEYS this loss has, one tensor
        keys: list[str] = []
        loss_keys: list[str] = []
        for epoch in range(self.cfg.num_epochs):
            # One gather per epoch, then contiguous slices: cheaper than indexing every minibatch.
            shuffled = flat[torch.randperm(n, generator=self._shuffle)]
            for start in range(0, n - mb + 1, mb):
                minibatch = shuffled[start : start + mb]
                if adaptive:  # rsl_rl: the KL before this step sets the step's learning rate
                    self._adapt_learning_rate(minibatch)
                with self.policy.encode_once(not self.compiled):  # shared encoder: once, 2 heads
                    out = self._loss_fn(minibatch)
                if not keys:
                    keys = [k for k in STAT_KEYS if k == "grad_norm" or k in out.keys()]
                    loss_keys = [k for k in LOSS_KEYS if k in keys]
                terms = {k: out[k] for k in loss_keys}
                total = terms["loss_objective"] + terms["loss_critic"]
                if self.cfg.entropy_coeff != 0.0:  # a hook may turn the term on or off
                    total = total + terms["loss_entropy"]
                else:
                    del terms["loss_entropy"]
                grad_norm = self.backward_and_step(
                    total, terms, f"PPO update (epoch {epoch}, minibatch {start // mb})"
                )
                rows.append(
                    torch.stack([grad_norm if k == "grad_norm" else out[k] for k in keys]).detach()
                )
        return rows, keys

    def _set_lr(self, lr: float) -> None:
        for group in self.optimizer.param_groups:
            group["lr"] = lr

    @torch.no_grad()
    def _adapt_learning_rate(self, minibatch: TensorDictBase) -> None:
        """``algorithm.desired_kl``: the KL of the current policy to the behaviour policy on this
        minibatch (averaged over ranks, so all ranks take the same rate) moves ``lr``; it lives in
        ``self.cfg`` so that ``hyperparameters()`` and checkpoints carry it."""
        net = self.policy.actor_net
        behaviour = {k: minibatch.get(BEHAVIOUR_PREFIX + k) for k in net.dist_keys}
        kl = net.kl(behaviour, minibatch.get("observation"))
        if self.grad_sync is not None:
            kl = kl.reshape(1).clone()
            self.grad_sync([kl])
        self.cfg.lr = adaptive_learning_rate(self.cfg.lr, float(kl), self.cfg.desired_kl)
        self._set_lr(self.cfg.lr)

    def _decide_fused(self) -> None:
        """The minibatch step for this run (once): fused (compiled as the loss would be) or today's."""
        if not self.use_fused_step:
            return
        problem = fused_unsupported(self)
        if problem is not None:
            log.info("[ppo] minibatch step: TorchRL's ClipPPOLoss (not fused: %s)", problem)
            return
        self.fused = FusedPPOStep(self, compiled=self.compiled)
        log.info("[ppo] minibatch step: fused (%s)", "compiled" if self.compiled else "eager")

    def _decide_compile(self, updates: int, mb: int) -> None:
        """Turn ``torch.compile`` of the loss on or off for this run (once, at the first update)."""
        self._compile_decided = True
        if self.compile == "false":
            return
        fused = self.use_fused_step and fused_unsupported(self) is None  # _decide_fused's choice
        saving = compile_saving_s(updates, mb, fused)
        if self.compile == "auto" and saving < AUTO_COMPILE_MIN_SAVING_S:
            log.info(
                "[ppo] algorithm.compile=auto: eager loss (%d minibatch updates in this run, "
                "estimated saving %.0f s < %.0f s)",
                updates,
                saving,
                AUTO_COMPILE_MIN_SAVING_S,
            )
            return
        problem = compile_unavailable(self.params[0].device if self.params else None)
        if problem is not None:  # (only auto gets here: true was checked at build time)
            log.warning("[ppo] algorithm.compile=auto: eager loss (%s)", problem)
            return
        log.info(
            "[ppo] torch.compile of the loss (algorithm.compile=%s; %d minibatch updates, estimated "
            "saving %.0f s): the first update compiles",
            self.compile,
            updates,
            saving,
        )
        compiled = torch.compile(self.loss, dynamic=False)

        def first_call(minibatch: TensorDictBase) -> TensorDictBase:
            from rlexp.checkpoints.files import rng_state, set_rng_state

            # Compiling (forward, and backward at the first backward) draws random numbers, and a
            # resumed run compiles at a different point than the run it continues: compile on a
            # throw-away call, put the RNGs back, then make the real call like every later one.
            t0 = time.perf_counter()
            rng = rng_state()
            failure: Exception | None = None
            try:
                warm = compiled(minibatch)
                sum(warm[k] for k in LOSS_KEYS if k in warm.keys()).backward()
            except Exception as exc:  # a backend failure: fall back unless the user insisted
                if self.compile == "true":
                    raise
                failure = exc
            finally:  # also on Ctrl-C: the checkpoint saved then must hold the run's own RNGs
                set_rng_state(rng)
                self.optimizer.zero_grad(set_to_none=True)
            if failure is not None:
                log.warning("[ppo] torch.compile failed, eager loss from here on: %s", failure)
                self._loss_fn, self.compiled = self.loss, False
                return self.loss(minibatch)
            log.info("[ppo] loss compiled in %.1f s", time.perf_counter() - t0)
            self._loss_fn = compiled
            return compiled(minibatch)

        self._loss_fn, self.compiled = first_call, True

    def _applied(self, name: str) -> None:
        """ClipPPOLoss holds the coefficients as buffers: change them in place."""
        value = float(getattr(self.cfg, name))
        if name in ("clip_epsilon", "entropy_coeff", "critic_coeff"):
            getattr(self.loss, name).fill_(value)

    def state_dict(self) -> dict:
        sd = {
            "optimizer": self.optimizer.state_dict(),
            "iteration": self.iteration,
            "hyperparameters": self.hyperparameters(),
        }
        if self.reward_normalizer is not None:
            sd["reward_normalizer"] = self.reward_normalizer.state_dict()
        return sd

    def load_state_dict(self, sd: dict) -> None:
        self.optimizer.load_state_dict(sd["optimizer"])
        self.iteration = int(sd["iteration"])
        self._load_hyperparameters(sd)
        if self.reward_normalizer is not None:
            saved = sd.get("reward_normalizer")
            if saved is None:
                log.warning(
                    "[ppo] algorithm.normalize_rewards=true, but the checkpoint has no reward "
                    "statistics (it was saved without it): they start afresh"
                )
            else:
                # The checkpoint holds rank 0's running returns; other ranks' envs start new
                # episodes on resume (Trainer.load_state_dict), so their returns start at 0.
                self.reward_normalizer.load_state_dict(saved, keep_returns=_is_rank_zero())


def _is_rank_zero() -> bool:
    import torch.distributed as dist

    return not (dist.is_available() and dist.is_initialized()) or dist.get_rank() == 0


def compile_unavailable(device: torch.device | None) -> str | None:
    """Why ``torch.compile`` (inductor) cannot run on ``device`` here, or None when it can."""
    if device is None or device.type == "cpu":
        compilers = [os.environ.get("CXX", ""), "g++", "c++", "clang++"]
        if not any(c and shutil.which(c) for c in compilers):
            return "no C++ compiler found (inductor needs one for CPU code; install g++ or set CXX)"
        return None
    if device.type == "cuda":
        try:
            import triton  # noqa: F401
        except ImportError:
            return "triton is not installed (inductor needs it for CUDA code)"
        return None
    return f"device {device.type} is not supported by rlexp's compiled loss"
