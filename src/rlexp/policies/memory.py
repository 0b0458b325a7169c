"""Recurrent policies (``policy.memory.type`` lstm / gru; docs/policies.md "Memory").

Each network reads its observation as the MLP policy's does (``inputs.ObsInput``: the normalised
vector, image features), then a recurrent core (torch's ``nn.LSTM`` / ``nn.GRU``, batch first),
then its MLP head, whose input is the core's output (``hidden_size``). Actor and critic each own a
core unless ``policy.memory.shared``: then the actor's core (reading the actor's observations)
feeds both heads and the critic's own core is absent.

The recurrent state, everywhere it lives (rollout, checkpoints, evaluation, export), is a dict of
float32 tensors ``actor_h``, ``actor_c`` (LSTM only), ``critic_h``, ``critic_c`` (absent when
shared), each ``[batch, num_layers, hidden_size]``; zeros are the state at an episode's start.

Why torch's modules and not TorchRL's ``LSTMModule`` / ``GRUModule``: those read and write the
state through TensorDict keys of their own layout and split a batch into trajectories at every
``is_init`` (padding them); rlexp's collector steps plain tensors, and the update runs each
minibatch of sequences as a few whole-batch calls between the steps where some sequence resets
(``RecurrentCore.sequence``), with the same kernels as collection.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from tensordict import TensorDictBase
from torch import nn

from rlexp.config.schema import MemoryConfig
from rlexp.policies.actor_critic import RECURRENT, ActorCritic, SamplingPolicy, _as_function
from rlexp.policies.heads import GaussianActorNet, ReadsObservation

#: A state in torch's layout: (h,) or (h, c), each [num_layers, batch, hidden].
TorchState = tuple[torch.Tensor, ...]


class RecurrentCore(nn.Module):
    """features [..., in_dim] -> ``nn.LSTM`` / ``nn.GRU`` -> [..., hidden_size]."""

    def __init__(self, kind: str, in_dim: int, hidden_size: int, num_layers: int) -> None:
        super().__init__()
        if kind not in ("lstm", "gru"):
            raise ValueError(f"policy.memory.type={kind!r}; choose from ['none', 'lstm', 'gru']")
        self.kind = kind
        self.hidden_size = hidden_size
        self.num_layers = num_layers
        cls = nn.LSTM if kind == "lstm" else nn.GRU
        self.rnn = cls(in_dim, hidden_size, num_layers, batch_first=True)

    @property
    def parts(self) -> tuple[str, ...]:
        """The state's parts: ``h`` and (LSTM) ``c``."""
        return ("h", "c") if self.kind == "lstm" else ("h",)

    def ortho_init(self) -> None:
        """Orthogonal weights (gain 1), zero biases: CleanRL's ``ppo_atari_lstm``."""
        for name, param in self.rnn.named_parameters():
            if name.startswith("weight"):
                nn.init.orthogonal_(param, 1.0)
            else:
                nn.init.zeros_(param)

    def _call(self, x: torch.Tensor, hx: TorchState) -> tuple[torch.Tensor, TorchState]:
        if self.kind == "lstm":
            y, (h, c) = self.rnn(x, (hx[0].contiguous(), hx[1].contiguous()))
            return y, (h, c)
        y, h = self.rnn(x, hx[0].contiguous())
        return y, (h,)

    def step(self, x: torch.Tensor, hx: TorchState) -> tuple[torch.Tensor, TorchState]:
        """One step of a batch: x [B, in_dim] -> y [B, hidden_size], the state after it."""
        y, hx = self._call(x.unsqueeze(1), hx)
        return y.squeeze(1), hx

    def sequence(
        self,
        x: torch.Tensor,
        hx: TorchState,
        is_init: torch.Tensor,
        at_reset: Callable[[int, TorchState], None] | None = None,
    ) -> tuple[torch.Tensor, TorchState]:
        """x [B, T, in_dim] from the state ``hx`` before step 0 -> y [B, T, hidden_size] and the
        state after the last step. The state is zeroed before every step where ``is_init`` [B, T]
        is True (an episode's first step): the time axis is cut where any row starts an episode,
        each piece one call of the whole batch. ``at_reset(t, hx)`` sees the state after step t-1,
        before it is zeroed, at each such cut (GAE's bootstrap values of ended episodes)."""
        steps = x.shape[1]
        cuts = torch.nonzero(is_init[:, 1:].any(0)).flatten().add(1).tolist()
        bounds = [0, *cuts, steps]
        outputs = []
        for start, end in zip(bounds[:-1], bounds[1:], strict=True):
            if start > 0 and at_reset is not None:
                at_reset(start, hx)
            keep = (~is_init[:, start]).to(x.dtype).reshape(1, -1, 1)
            hx = tuple(h * keep for h in hx)
            y, hx = self._call(x[:, start:end], hx)
            outputs.append(y)
        return (outputs[0] if len(outputs) == 1 else torch.cat(outputs, 1)), hx


def to_torch(state: dict[str, torch.Tensor], prefix: str, parts: tuple[str, ...]) -> TorchState:
    """``state``'s ``{prefix}_h`` (and ``_c``) [B, layers, H] in torch's [layers, B, H]."""
    return tuple(state[f"{prefix}_{p}"].transpose(0, 1) for p in parts)


def from_torch(hx: TorchState, prefix: str, parts: tuple[str, ...]) -> dict[str, torch.Tensor]:
    """torch's [layers, B, H] state as ``{prefix}_h`` (and ``_c``) [B, layers, H] entries."""
    return {f"{prefix}_{p}": h.transpose(0, 1).contiguous() for p, h in zip(parts, hx, strict=True)}


def flat_features(net: ReadsObservation, obs: torch.Tensor | TensorDictBase) -> torch.Tensor:
    """``net``'s input features of observations [B, T, ...] -> [B, T, F] (images through the
    encoders as one batch)."""
    b, t = obs.shape[:2]
    flat = obs.reshape(b * t) if isinstance(obs, TensorDictBase) else obs.reshape(b * t, -1)
    return net.features(flat).reshape(b, t, -1)


class RecurrentActorCritic(ActorCritic):
    """The actor-critic with a recurrent core per network (or one shared): the API evaluation and
    export use is ``recurrent``, ``memory_spec``, ``initial_state``, ``reset_state``, ``act``."""

    recurrent = True

    def _core_outputs(self, cfg, actor_dim: int, critic_dim: int | None) -> tuple[int, int | None]:
        memory: MemoryConfig = cfg.memory
        self.memory_cfg = memory
        self.actor_core = RecurrentCore(
            memory.type, actor_dim, memory.hidden_size, memory.num_layers
        )
        self.critic_core: RecurrentCore | None = None
        if critic_dim is not None and not memory.shared:
            self.critic_core = RecurrentCore(
                memory.type, critic_dim, memory.hidden_size, memory.num_layers
            )
        if cfg.ortho_init:
            for core in (self.actor_core, self.critic_core):
                if core is not None:
                    core.ortho_init()
        return memory.hidden_size, (None if critic_dim is None else memory.hidden_size)

    # -- the state ---------------------------------------------------------------------------------
    @property
    def state_names(self) -> list[str]:
        """The state's entries: actor_h, actor_c (LSTM), critic_h, critic_c (not shared)."""
        parts = self.actor_core.parts
        names = [f"actor_{p}" for p in parts]
        if self.critic_core is not None:
            names += [f"critic_{p}" for p in parts]
        return names

    @property
    def memory_spec(self) -> dict:
        """The memory's settings and state layout (metadata: checkpoints, export)."""
        m = self.memory_cfg
        shape = [m.num_layers, m.hidden_size]
        return {
            "type": m.type,
            "hidden_size": m.hidden_size,
            "num_layers": m.num_layers,
            "shared": m.shared,
            "state": [{"name": n, "shape": ["batch", *shape]} for n in self.state_names],
            "reset": "zeros at episode start",
        }

    def initial_state(
        self, batch_size: int, device: torch.device | str | None = None
    ) -> dict[str, torch.Tensor]:
        """The state at an episode's start for ``batch_size`` envs: zeros [B, layers, H] each."""
        if device is None:
            device = next(self.parameters()).device
        m = self.memory_cfg
        return {
            n: torch.zeros(batch_size, m.num_layers, m.hidden_size, device=device)
            for n in self.state_names
        }

    @staticmethod
    def reset_state(state: dict[str, torch.Tensor], done: torch.Tensor) -> dict[str, torch.Tensor]:
        """``state`` with the rows where ``done`` ([B] or [B, 1] bool) is True zeroed (new dict)."""
        keep = (~done.reshape(-1)).to(torch.float32).reshape(-1, 1, 1)
        return {k: v * keep.to(v.device, v.dtype) for k, v in state.items()}

    def act(
        self,
        obs: torch.Tensor | TensorDictBase,
        state: dict[str, torch.Tensor],
        deterministic: bool = True,
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """One step of a batch of envs: (action, the state after it). The critic's entries pass
        through unchanged (acting needs no value); resetting at an episode's end is the caller's
        (``reset_state``)."""
        with torch.no_grad():
            out, new = self.sampling_policy(deterministic).sampler()(obs, state, critic=False)
        return out[-2], new

    def sampling_policy(self, deterministic: bool = False) -> RecurrentSamplingPolicy:
        return RecurrentSamplingPolicy(self, deterministic)

    # -- training ----------------------------------------------------------------------------------
    def head_params(self, y: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """The actor head's distribution parameters (``dist_keys`` order) from core outputs."""
        net = self.actor_net
        out = net.mlp(y)
        if isinstance(net, GaussianActorNet):
            return out, net.log_scale().exp().expand_as(out)
        return (out,)

    def sequence_outputs(
        self,
        obs: torch.Tensor | TensorDictBase,
        state: dict[str, torch.Tensor],
        is_init: torch.Tensor,
    ) -> tuple[tuple[torch.Tensor, ...], torch.Tensor]:
        """Sequences [S, L, ...] from their starting ``state`` (``is_init`` [S, L]: where the state
        is zeroed first) -> (the actor's distribution parameters [S, L, ...], values [S, L, 1])."""
        actor_x = flat_features(self.actor_net, obs)
        y, _ = self.actor_core.sequence(
            actor_x, to_torch(state, "actor", self.actor_core.parts), is_init
        )
        if self.critic_core is None:
            critic_y = y
        else:
            critic_x = flat_features(self.critic_net, obs)
            hx = to_torch(state, "critic", self.critic_core.parts)
            critic_y, _ = self.critic_core.sequence(critic_x, hx, is_init)
        return self.head_params(y), self.critic_net.mlp(critic_y)

    @torch.no_grad()
    def rollout_values(
        self,
        obs: torch.Tensor | TensorDictBase,
        next_obs: torch.Tensor | TensorDictBase,
        state: dict[str, torch.Tensor],
        is_init: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """V(s_t) and V(s'_t) [E, T, 1] over a rollout [E, T] in order, from the state stored at
        its first step, carried and zeroed where an episode starts (``is_init``). V(s'_t) is
        V(s_t+1) within an episode; where one ended (the next step starts another) and at the
        last step, the critic steps once more on the step's own next observation from the state
        after the step (a truncated episode's bootstrap)."""
        core = self.critic_core or self.actor_core
        net: ReadsObservation = self.critic_net if self.critic_core is not None else self.actor_net
        prefix = "critic" if self.critic_core is not None else "actor"
        x = flat_features(net, obs)
        ends: list[tuple[int, torch.Tensor, TorchState]] = []  # (step, envs, state after it)

        def at_reset(t: int, hx: TorchState) -> None:
            envs = torch.nonzero(is_init[:, t]).flatten()
            ends.append((t - 1, envs, tuple(h[:, envs] for h in hx)))

        y, last = core.sequence(x, to_torch(state, prefix, core.parts), is_init, at_reset)
        steps = x.shape[1]
        ends.append((steps - 1, torch.arange(x.shape[0], device=x.device), last))
        value = self.critic_net.mlp(y)
        next_value = torch.empty_like(value)
        next_value[:, :-1] = value[:, 1:]
        envs = torch.cat([e for _, e, _ in ends])
        times = torch.cat([torch.full_like(e, t) for t, e, _ in ends])
        hx = tuple(torch.cat([s[i] for _, _, s in ends], 1) for i in range(len(core.parts)))
        boot_x = net.features(next_obs[envs, times])
        boot_y, _ = core.step(boot_x, hx)
        next_value[envs, times] = self.critic_net.mlp(boot_y)
        return value, next_value


class RecurrentSamplingPolicy(SamplingPolicy):
    """Collection (and evaluation) policy of a recurrent actor-critic: ``sampler()`` gives
    ``(obs, state) -> (the out_keys' tensors, the state after the step)``; the collector carries
    the state and zeroes it where an episode ended. Torch only (no numpy sampler)."""

    use_numpy = False

    def __init__(self, policy: RecurrentActorCritic, deterministic: bool = False) -> None:
        super().__init__(policy.actor_net, deterministic)
        object.__setattr__(
            self, "_policy", policy
        )  # not a submodule: its parameters are the policy's
        self.state_names = policy.state_names

    @property
    def recurrent(self) -> bool:
        return True

    def initial_state(self, batch_size: int, device=None) -> dict[str, torch.Tensor]:
        return self._policy.initial_state(batch_size, device)

    def sampler(self) -> Callable[..., tuple[tuple[torch.Tensor, ...], dict[str, torch.Tensor]]]:
        """``(obs, state, critic=True) -> (out_keys' tensors, new state)``: the actor head's
        sampler with the core as its first layer (the same draws as the MLP policy's sampler),
        then (``critic``) the critic's core one step."""
        policy = self._policy
        actor_core, critic_core = policy.actor_core, policy.critic_core
        parts = actor_core.parts
        carried: dict[str, TorchState] = {}

        def core_layer(x: torch.Tensor) -> torch.Tensor:
            y, carried["actor"] = actor_core.step(x, carried["actor"])
            return y

        layers = [core_layer, *(_as_function(m) for m in self.actor_net.mlp)]
        head = self.actor_net.sampler(self.deterministic, layers)
        critic_input = policy.critic_net.input_function()

        def sample(obs, state: dict[str, torch.Tensor], critic: bool = True):
            carried["actor"] = to_torch(state, "actor", parts)
            out = head(obs)
            new = dict(state)
            new.update(from_torch(carried.pop("actor"), "actor", parts))
            if critic and critic_core is not None:
                _, hx = critic_core.step(critic_input(obs), to_torch(state, "critic", parts))
                new.update(from_torch(hx, "critic", parts))
            return out, new

        return sample

    def sample(self, obs: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """Stateless use (TorchRL's loop, a probe): one step from the episode-start state."""
        state = self.initial_state(obs.shape[0], obs.device)
        return self.sampler()(obs, state)[0]


RECURRENT[ActorCritic] = RecurrentActorCritic
