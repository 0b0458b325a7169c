"""A small batched torch env with the observation contract of issue #47 (DESIGN47 §1): each step's
``observation`` is a TensorDict of ``"vector"`` (float32 [N, 4]) and ``"pixels"`` (uint8 [N, C, H, W]),
for the tests of the training loop with image observations (tests/test_image_training.py).

Named in configs as ``env.backend=torchrl env.name=image_envs:make_image_env``: it is already in rlexp's
shape (``step_action``, ``autoreset_observation``, ``obs_layout``, ``env_state``), so the factory
takes it as it is. N agents on an H x W grid each move towards a goal; the image shows the agent
(channel 0, 255), the goal (channel 1, 200) and noise drawn from the env's own generator (the other
channels), so a resume must restore that generator to be exact; the vector is the agent's position,
the goal's, scaled to [-1, 1]. Episodes end on reaching the goal (terminated) or after ``max_len``
steps (truncated). Constants asymmetric on purpose (an image 3 x 12 x 10 by default).
"""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from rlexp.envs.spaces import ObsLayout, ObsPart

VECTOR = 4


class ImageReach(EnvBase):
    """rlexp's env shape with a structured observation (vector + uint8 CHW image)."""

    def __init__(
        self,
        num_envs: int = 3,
        seed: int = 0,
        channels: int = 3,
        height: int = 12,
        width: int = 10,
        max_len: int = 7,
        device: str = "cpu",
    ) -> None:
        super().__init__(batch_size=torch.Size([num_envs]), device=device)
        n, c, h, w = num_envs, channels, height, width
        self.env_id, self.num_envs, self.max_len = "image_envs:ImageReach", n, max_len
        self.image_shape = (c, h, w)
        self.obs_layout = ObsLayout(
            "Composite",
            (
                ObsPart("state", "box", (VECTOR,), 0, VECTOR),
                ObsPart(
                    "pixels", "image", (c, h, w), -1, 0, image_key="pixels", source_layout="chw"
                ),  # fmt: skip
            ),
            VECTOR,
        )
        dev = self.device
        self.observation_spec = Composite(
            observation=Composite(
                vector=Unbounded(shape=(n, VECTOR), dtype=torch.float32, device=dev),
                pixels=Bounded(0, 255, shape=(n, c, h, w), dtype=torch.uint8, device=dev),
                shape=(n,),
                device=dev,
            ),
            shape=(n,),
            device=dev,
        )
        self.action_spec = Bounded(-1.0, 1.0, shape=(n, 2), dtype=torch.float32, device=dev)
        self.reward_spec = Unbounded(shape=(n, 1), dtype=torch.float32, device=dev)
        flag = lambda: Categorical(2, shape=(n, 1), dtype=torch.bool, device=dev)  # noqa: E731
        self.done_spec = Composite(
            done=flag(), terminated=flag(), truncated=flag(), shape=(n,), device=dev
        )
        self.gen = torch.Generator().manual_seed(seed)
        self.pos = torch.zeros(n, 2)
        self.goal = torch.zeros(n, 2)
        self.length = torch.zeros(n, dtype=torch.long)
        self._base_seed: int | None = seed
        self._restored = False
        self.resume_mode: str | None = None
        self.steps = 0
        self._new_episodes(torch.ones(n, dtype=torch.bool))
        self.obs_now = self._observe()

    # -- the task ----------------------------------------------------------------------------------
    def _new_episodes(self, mask: torch.Tensor) -> None:
        c, h, w = self.image_shape
        hw = torch.tensor([h - 1, w - 1], dtype=torch.float32)
        pos = torch.floor(torch.rand(self.num_envs, 2, generator=self.gen) * (hw + 1))
        goal = torch.floor(torch.rand(self.num_envs, 2, generator=self.gen) * (hw + 1))
        m = mask.unsqueeze(-1)
        self.pos = torch.where(m, pos, self.pos)
        self.goal = torch.where(m, goal, self.goal)
        self.length = torch.where(mask, torch.zeros_like(self.length), self.length)

    def _observe(self) -> TensorDict:
        c, h, w = self.image_shape
        n = self.num_envs
        img = torch.randint(0, 40, (n, c, h, w), generator=self.gen, dtype=torch.uint8)
        rows = torch.arange(n)
        p, g = self.pos.long(), self.goal.long()
        img[rows, 0, p[:, 0], p[:, 1]] = 255
        if c > 1:
            img[rows, 1, g[:, 0], g[:, 1]] = 200
        scale = torch.tensor([h - 1, w - 1], dtype=torch.float32)
        vector = torch.cat([self.pos / scale * 2 - 1, self.goal / scale * 2 - 1], -1)
        return TensorDict({"vector": vector, "pixels": img}, batch_size=[n])

    def step_tensors(self, action: torch.Tensor) -> dict:
        c, h, w = self.image_shape
        hi = torch.tensor([h - 1, w - 1], dtype=torch.float32)
        move = torch.round(action.clamp(-1, 1) * torch.tensor([1.0, 2.0]))
        self.pos = torch.minimum(torch.maximum(self.pos + move, torch.zeros(2)), hi)
        self.length += 1
        dist = (self.goal - self.pos).abs().sum(-1)
        reward = (-0.1 * dist - 0.01 * action.pow(2).sum(-1)).unsqueeze(-1)
        terminated = (dist == 0).unsqueeze(-1)
        truncated = (self.length >= self.max_len).unsqueeze(-1) & ~terminated
        done = terminated | truncated
        final = self._observe()
        self.steps += 1
        if done.any():
            self._new_episodes(done.squeeze(-1))
            fresh = self._observe()
            mask = done.squeeze(-1)
            self.obs_now = TensorDict(
                {k: torch.where(mask.view(-1, *[1] * (v.dim() - 1)), fresh[k], v)
                 for k, v in final.items()},
                batch_size=[self.num_envs],
            )  # fmt: skip
        else:
            self.obs_now = final
        return {"observation": final, "reward": reward, "done": done,
                "terminated": terminated, "truncated": truncated}  # fmt: skip

    # -- rlexp's env shape -------------------------------------------------------------------------
    def step_action(self, action: torch.Tensor) -> TensorDictBase:
        return TensorDict(self.step_tensors(action), batch_size=self.batch_size)

    def autoreset_observation(self, next_td) -> TensorDict:
        return self.obs_now

    def check_first_step(self) -> None:
        self.reset()
        self.step_action(torch.zeros(self.action_spec.shape))

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        masked = tensordict is not None and "_reset" in tensordict.keys()
        if self._restored:
            self._restored = False
        elif not masked:
            self._new_episodes(torch.ones(self.num_envs, dtype=torch.bool))
            self.obs_now = self._observe()
        return TensorDict({"observation": self.obs_now.clone()}, batch_size=self.batch_size)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        return self.step_action(tensordict.get("action"))

    def _set_seed(self, seed: int | None) -> None:
        if seed is not None:
            self._base_seed = int(seed)
            self.gen.manual_seed(int(seed))

    def env_state(self, strict: bool = False) -> dict:
        return {
            "env_id": self.env_id,
            "num_envs": self.num_envs,
            "pos": self.pos.clone(),
            "goal": self.goal.clone(),
            "length": self.length.clone(),
            "rng": self.gen.get_state(),
            "obs": self.obs_now.to_dict(),
            "steps": self.steps,
        }

    def load_env_state(self, sd: dict) -> None:
        self.pos, self.goal = sd["pos"].clone(), sd["goal"].clone()
        self.length = sd["length"].clone()
        self.gen.set_state(sd["rng"])
        self.obs_now = TensorDict(dict(sd["obs"]), batch_size=[self.num_envs])
        self.steps = int(sd["steps"])
        self._restored = True
        self.resume_mode = "restored (the env's state)"


def make_image_env(
    num_envs: int,
    device: str,
    seed: int,
    channels: int = 3,
    height: int = 12,
    width: int = 10,
    max_len: int = 7,
) -> ImageReach:
    """The factory a config names: ``env.name=image_envs:make_image_env``."""
    return ImageReach(num_envs, seed, channels, height, width, max_len, device)
