"""Evaluation of a recurrent policy (#48, ``policy.memory.type`` lstm / gru): an eval round carries
the actor's state from step to step, per env copy, and starts each episode from zeros, exactly as a
hand-written loop of single Gymnasium envs and plain ``nn.LSTM`` / ``nn.GRU`` calls does (both of
rlexp's loops: the lean one and TorchRL's); the eval worker (``trainer.eval_async``) gives the
in-process round's numbers exactly."""

from __future__ import annotations

import dataclasses

import gymnasium as gym
import numpy as np
import pytest
import torch

from conftest import compose
from rlexp.config.validate import to_root_config

#: Hopper-v5 (real-valued rewards, episodes that end at different steps on each copy), 3 copies and
#: 5 episodes (quotas 2, 2, 1), a 2-layer memory of 16 units (not the defaults).
EPISODES, COPIES, SEED = 5, 3, 11


def _config(memory: str):
    return to_root_config(
        compose(
            [
                "env=hopper",
                "env.max_episode_steps=60",
                f"policy.memory.type={memory}",
                "policy.memory.hidden_size=16",
                "policy.memory.num_layers=2",
                "policy.ortho_init=false",
                "policy.actor.hidden_sizes=[32]",
            ]
        )
    )


def _policy(config, env):
    """The configured recurrent policy with weights that make its state matter: a normaliser with
    statistics, an action head large enough to saturate the bounds."""
    from rlexp.policies.actor_critic import policy_for_env

    torch.manual_seed(3)
    policy = policy_for_env(config.policy, config.env, env)
    with torch.no_grad():
        policy.normalizer.update(torch.randn(500, policy.obs_layout.dim) * 2.0 + 0.5)
        policy.actor_net.mlp[-1].weight.mul_(6.0)
    return policy


def _reference(policy, config, reset: str) -> list[tuple[float, int]]:
    """Each copy's first episodes (its quota: 2, 2, 1) on its own Gymnasium env, seeded as rlexp
    seeds copy i (``seed + i`` at the first reset), acting with the actor's features, a plain call
    of its ``nn.LSTM`` / ``nn.GRU`` and its MLP (the Gaussian's mean, clipped to the bounds as the
    env clips). ``reset``: ``episode`` (the rule), ``never`` (the state runs on across episodes) or
    ``step`` (no memory at all), the last two only to show the rule is what the eval follows."""
    rnn, lstm = policy.actor_core.rnn, policy.memory_cfg.type == "lstm"
    layers, hidden = rnn.num_layers, rnn.hidden_size
    quota = [EPISODES // COPIES + (i < EPISODES % COPIES) for i in range(COPIES)]
    out = []
    for i in range(COPIES):
        env = gym.make(config.env.name, max_episode_steps=config.env.max_episode_steps)
        low, high = (
            torch.as_tensor(b, dtype=torch.float32)
            for b in (env.action_space.low, env.action_space.high)
        )
        obs, _ = env.reset(seed=SEED + i)
        h = c = torch.zeros(layers, 1, hidden)
        for _ in range(quota[i]):
            if reset == "episode":
                h = c = torch.zeros(layers, 1, hidden)
            total, steps, done = 0.0, 0, False
            while not done:
                if reset == "step":
                    h = c = torch.zeros(layers, 1, hidden)
                with torch.no_grad():
                    x = policy.actor_net.features(torch.as_tensor(obs, dtype=torch.float32)[None])
                    if lstm:
                        y, (h, c) = rnn(x[:, None], (h, c))
                    else:
                        y, h = rnn(x[:, None], h)
                    action = torch.clamp(policy.actor_net.mlp(y[:, 0])[0], low, high)
                obs, reward, terminated, truncated, _ = env.step(action.numpy())
                total += float(np.float32(reward))
                steps += 1
                done = terminated or truncated
            out.append((total, steps))
            obs, _ = env.reset()
        env.close()
    return out


def _metrics(episodes: list[tuple[float, int]]) -> dict[str, float]:
    returns = [r for r, _ in episodes]
    return {
        "eval/episode_return": float(np.mean(returns)),
        "eval/episode_return_std": float(np.std(returns)),
        "eval/episode_length": float(np.mean([n for _, n in episodes])),
    }


@pytest.mark.parametrize("memory", ["lstm", "gru"])
def test_an_eval_round_carries_the_state_and_zeroes_it_per_episode_as_a_hand_written_loop(memory):
    from rlexp.envs.factory import make_env
    from rlexp.training.evaluation import RecurrentActor, run_episodes, run_round

    config = _config(memory)
    env = make_env(config.env, COPIES, SEED)
    try:
        policy = _policy(config, env)
        lean = run_round(env, policy, EPISODES, SEED)  # the trainer's round: the lean loop
        env.set_seed(SEED)
        generic = run_episodes(env, RecurrentActor(policy), EPISODES, lean=False)  # TorchRL's
    finally:
        env.close()
    want = _metrics(_reference(policy, config, "episode"))
    assert generic.pop("eval/episodes") == EPISODES
    assert lean == pytest.approx(want, rel=1e-6) and generic == pytest.approx(want, rel=1e-6)
    lengths = [n for _, n in _reference(policy, config, "episode")]
    assert len(set(lengths)) > 1, f"every episode {lengths[0]} steps: copies end together"
    for other in ("never", "step"):  # the state's handling changes the numbers: not vacuous
        wrong = _metrics(_reference(policy, config, other))["eval/episode_return"]
        assert wrong != pytest.approx(want["eval/episode_return"], rel=1e-3), other


def test_the_eval_worker_gives_the_in_process_round_exactly():
    """``trainer.eval_async``: the worker builds its own env and recurrent policy, loads the
    snapshot and runs the same round: the same metrics, to the last bit."""
    from rlexp.envs.factory import make_env
    from rlexp.training.eval_worker import EvalRound, EvalSetup, EvalWorker
    from rlexp.training.evaluation import run_round

    config = _config("lstm")
    env = make_env(config.env, COPIES, SEED)
    try:
        policy = _policy(config, env)
        want = run_round(env, policy, EPISODES, SEED)
    finally:
        env.close()
    setup = EvalSetup(dataclasses.replace(config.env, num_eval_envs=COPIES), config.policy, SEED,
                      EPISODES)  # fmt: skip
    worker = EvalWorker(setup, timeout_s=120.0)
    try:  # (closed, or killed, on the way out whatever happens)
        worker.submit(EvalRound(7, {"policy": policy.state_dict()}))
        done, got = worker.result()
    finally:
        worker.close()
    assert done.step == 7 and got == want
