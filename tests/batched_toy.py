"""A small batched torch env for the tests of env.backend=vecenv / torchrl (docs/batched_envs.md).

N point masses in a plane, physics in torch on any device: each pushes itself (a force per axis,
the axes unequal) towards its own goal; an episode ends by leaving the arena (terminated) or at
``max_episode_length`` steps (a time-out, counted per env in ``episode_length_buf``). Observation
(7): position (2), velocity (2), goal - position (2), the episode's phase (length / limit). The
constants are asymmetric on purpose, so that a swapped axis or a default shows in the numbers.

Offered through both contracts: ``ToyVecEnv`` (rsl_rl's VecEnv, with ``get_state`` / ``set_state``
and ``seed``; its observation as a tensor, rsl_rl 2.x's tuple or rsl_rl 3.x's dict of groups) and
``ToyTorchRLEnv`` (a TorchRL EnvBase without state: a resume restarts its episodes).
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import torch
from tensordict import TensorDict
from torchrl.data import Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

DT = 0.2
FORCE = (3.0, 1.5)  # per axis
MASS = 1.3
DAMPING = 0.25  # the share of velocity lost per step
ARENA = 2.0  # |position| beyond this on either axis: terminated
ACTION_LOW, ACTION_HIGH = (-1.0, -2.0), (1.0, 2.0)
MAX_LEN = 19


class ToyPhysics:
    """The state of N envs and one step of all of them (no reset: the callers decide)."""

    def __init__(self, num_envs: int, device: str, seed: int, max_len: int = MAX_LEN) -> None:
        self.n, self.device, self.max_len = num_envs, torch.device(device), max_len
        self.gen = torch.Generator(device=self.device).manual_seed(seed)
        self.force = torch.tensor(FORCE, device=self.device)
        z = torch.zeros(num_envs, 2, device=self.device)
        self.pos, self.vel, self.goal = z.clone(), z.clone(), z.clone()
        self.length = torch.zeros(num_envs, dtype=torch.long, device=self.device)
        self.reset(torch.ones(num_envs, dtype=torch.bool, device=self.device))

    def _uniform(self, rows: int, scale: float) -> torch.Tensor:
        u = torch.rand(rows, 2, generator=self.gen, device=self.device)
        return (2 * u - 1) * scale

    def reset(self, mask: torch.Tensor) -> None:
        """New episodes for the envs of ``mask`` (drawn for all envs: the same RNG use always)."""
        pos, goal = self._uniform(self.n, 1.0), self._uniform(self.n, 1.5)
        m = mask.unsqueeze(-1)
        self.pos = torch.where(m, pos, self.pos)
        self.goal = torch.where(m, goal, self.goal)
        self.vel = torch.where(m, torch.zeros_like(self.vel), self.vel)
        self.length = torch.where(mask, torch.zeros_like(self.length), self.length)

    def step(self, action: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """(reward [N], terminated [N], time_out [N]) after one step."""
        self.vel = (1 - DAMPING) * self.vel + DT * self.force * action / MASS
        self.pos = self.pos + DT * self.vel
        self.length = self.length + 1
        dist = (self.goal - self.pos).norm(dim=-1)
        reward = -dist - 0.01 * action.pow(2).sum(-1)
        terminated = (self.pos.abs() > ARENA).any(-1)
        return reward, terminated, self.length >= self.max_len

    def obs(self) -> torch.Tensor:
        phase = (self.length.float() / self.max_len).unsqueeze(-1)
        return torch.cat([self.pos, self.vel, self.goal - self.pos, phase], -1)

    def state(self) -> dict:
        return {
            "pos": self.pos.clone(),
            "vel": self.vel.clone(),
            "goal": self.goal.clone(),
            "length": self.length.clone(),
            "rng": self.gen.get_state(),
        }

    def load(self, state: dict) -> None:
        for key in ("pos", "vel", "goal", "length"):
            value = state[key]
            assert value.device.type == self.device.type, f"{key} on {value.device}"
            setattr(self, key, value.clone())
        self.gen.set_state(state["rng"])


class ToyVecEnv:
    """rsl_rl's VecEnv contract over ``ToyPhysics``.

    ``obs_format``: ``tensor`` | ``tuple`` (rsl_rl 2.x) | ``dict`` (rsl_rl 3.x groups; ``critic``:
    with a "critic" group);
    ``final_obs``: hand the true final observations over in ``extras["final_observation"]``;
    ``bad``: break the contract one way (obs_shape, obs_dtype, device, reward_shape)."""

    def __init__(
        self,
        num_envs: int = 4,
        device: str = "cpu",
        seed: int = 0,
        obs_format: str = "tensor",
        final_obs: bool = True,
        action_space: bool = True,
        bad: str | None = None,
        max_episode_length: int = MAX_LEN,
        critic: bool = True,
    ) -> None:
        self.num_envs, self.num_actions, self.device = num_envs, 2, device
        self.critic = critic  # dict: a "critic" group (2x the policy's) beside "policy"
        self.max_episode_length = max_episode_length
        self.physics = ToyPhysics(num_envs, device, seed, max_episode_length)
        self.obs_format, self.final_obs, self.bad = obs_format, final_obs, bad
        if action_space:
            low, high = np.array(ACTION_LOW, np.float32), np.array(ACTION_HIGH, np.float32)
            self.single_action_space = gym.spaces.Box(low, high, dtype=np.float32)

    @property
    def episode_length_buf(self) -> torch.Tensor:
        return self.physics.length

    def _form(self, obs: torch.Tensor):
        if self.bad == "obs_dtype":
            obs = obs.long()
        elif self.bad == "device":
            obs = obs.to("meta")
        if self.obs_format == "tuple":
            return obs, {"observations": {}}
        if self.obs_format == "dict":
            groups = {"policy": obs, "critic": obs * 2} if self.critic else {"policy": obs}
            return TensorDict(groups, batch_size=[self.num_envs])
        return obs

    def get_observations(self):
        return self._form(self.physics.obs())

    def reset(self):
        p = self.physics
        p.reset(torch.ones(p.n, dtype=torch.bool, device=p.device))
        return self.get_observations(), {}

    def seed(self, seed: int = -1) -> int:
        self.physics.gen.manual_seed(seed)
        return seed

    def step(self, actions: torch.Tensor):
        assert (
            actions.shape == (self.num_envs, 2) and actions.device.type == self.physics.device.type
        )
        p = self.physics
        reward, terminated, time_outs = p.step(actions)
        dones = terminated | time_outs
        final = p.obs()
        p.reset(dones)
        obs = p.obs()
        if self.bad == "obs_shape":
            obs = obs[:, :6]
        if self.bad == "reward_shape":
            reward = reward.unsqueeze(-1).expand(-1, 2)
        extras = {"time_outs": time_outs, "log": {}}
        if self.final_obs:
            extras["final_observation"] = self._form(final)
        return self._form(obs), reward, dones.long(), extras  # dones as Isaac Lab gives them

    def get_state(self) -> dict:
        return self.physics.state()

    def set_state(self, state: dict) -> None:
        self.physics.load(state)

    def close(self) -> None:
        self.closed = True


def make_vecenv(num_envs: int, device: str, seed: int, **kwargs) -> ToyVecEnv:
    """The factory a config names: ``env.name=batched_toy:make_vecenv``."""
    return ToyVecEnv(num_envs, device, seed, **kwargs)


def make_vecenv_of_three(seed: int = 0) -> ToyVecEnv:
    """A factory without a num_envs parameter: the env keeps its own count (3)."""
    return ToyVecEnv(3, "cpu", seed)


NOT_CALLABLE = 3


class ToyTorchRLEnv(EnvBase):
    """The same physics as a TorchRL EnvBase: nested observation entries, unbounded actions, no
    state protocol (a resume starts new episodes, seeded)."""

    def __init__(self, num_envs: int = 4, device: str = "cpu", seed: int = 0) -> None:
        super().__init__(batch_size=torch.Size([num_envs]), device=device)
        n = num_envs
        self.physics = ToyPhysics(n, device, seed)

        def box(k: int) -> Unbounded:
            return Unbounded(shape=(n, k), dtype=torch.float32, device=self.device)

        self.observation_spec = Composite(
            position=box(2),
            velocity=box(2),
            phase=box(1),
            task=Composite(to_goal=box(2), shape=(n,), device=self.device),
            shape=(n,),
            device=self.device,
        )
        self.action_spec = box(2)
        self.reward_spec = box(1)
        flag = Categorical(2, shape=(n, 1), dtype=torch.bool, device=self.device)
        self.done_spec = Composite(
            done=flag,
            terminated=flag.clone(),
            truncated=flag.clone(),
            shape=(n,),
            device=self.device,
        )

    def _observation(self, **flags: torch.Tensor) -> TensorDict:
        p = self.physics
        phase = (p.length.float() / p.max_len).unsqueeze(-1)
        return TensorDict(
            {
                "position": p.pos.clone(),
                "velocity": p.vel.clone(),
                "phase": phase,
                "task": {"to_goal": p.goal - p.pos},
                **flags,
            },
            batch_size=self.batch_size,
            device=self.device,
        )

    def _reset(self, tensordict=None, **kwargs) -> TensorDict:
        p = self.physics
        mask = torch.ones(p.n, dtype=torch.bool, device=p.device)
        if tensordict is not None and "_reset" in tensordict.keys():
            mask = tensordict.get("_reset").reshape(-1)
        p.reset(mask)
        zeros = torch.zeros(p.n, 1, dtype=torch.bool, device=p.device)
        return self._observation(done=zeros, terminated=zeros.clone(), truncated=zeros.clone())

    def _step(self, tensordict) -> TensorDict:
        reward, terminated, time_out = self.physics.step(tensordict.get("action"))
        return self._observation(
            reward=reward.unsqueeze(-1),
            done=(terminated | time_out).unsqueeze(-1),
            terminated=terminated.unsqueeze(-1),
            truncated=(time_out & ~terminated).unsqueeze(-1),
        )

    def _set_seed(self, seed: int | None) -> None:
        if seed is not None:
            self.physics.gen.manual_seed(seed)


def make_torchrl_env(num_envs: int, device: str, seed: int) -> ToyTorchRLEnv:
    """The factory a config names: ``env.name=batched_toy:make_torchrl_env``."""
    return ToyTorchRLEnv(num_envs, device, seed)
