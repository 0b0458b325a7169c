"""``env.backend=gymnasium_async`` across resets and signals (issue #44 item 3).

- Successive full resets, and a masked reset of some copies, start new episodes: each copy ``i`` is
  seeded ``seed + i`` at the first full reset only and continues its own RNG stream after, as plain
  Gymnasium's ``reset(seed=...)`` then ``reset()`` does (the reference, one env per copy) and as
  the in-process backend does. A worker reseeded at every reset repeats its first episode.
- The workers lead process groups of their own: a terminal's Ctrl-C (SIGINT to the foreground
  process group) reaches the training process only, which stops at its safe point; workers that
  took the SIGINT too would die under it (their KeyboardInterrupt), and the stop checkpoint could
  not read their envs. The end-to-end run (a stop checkpoint that holds the workers' MuJoCo state,
  restored on resume) is tests/test_vector_backends.py's Ctrl-C test.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys

import gymnasium as gym
import numpy as np
import pytest
import torch
from tensordict import TensorDict

from conftest import REPO

pytest.importorskip("mujoco")


def _plain_resets(env_id: str, seed: int, n: int, counts: list[int]) -> list[list[np.ndarray]]:
    """Copy ``i``'s first ``counts[i]`` reset observations in plain Gymnasium: seeded ``seed + i``
    once, then ``reset()`` (float32, as rlexp flattens them)."""
    out = []
    for i in range(n):
        env = gym.make(env_id)
        try:
            obs = [env.reset(seed=seed + i)[0]] + [env.reset()[0] for _ in range(counts[i] - 1)]
        finally:
            env.close()
        out.append([np.asarray(o, dtype=np.float32) for o in obs])
    return out


def _resets(env) -> list[torch.Tensor]:
    """Full reset, full reset, a reset of copies 0 and 2 only (TorchRL's ``_reset`` mask), full."""
    mask = TensorDict({"_reset": torch.tensor([[True], [False], [True]])}, batch_size=[3])
    return [
        env.reset()["observation"].clone(),
        env.reset()["observation"].clone(),
        env.reset(mask)["observation"].clone(),
        env.reset()["observation"].clone(),
    ]


@pytest.mark.parametrize("env_id", ["CartPole-v1", "Hopper-v5"])
def test_successive_and_masked_resets_start_new_episodes_as_in_process_and_plain_gymnasium(env_id):
    from rlexp.envs.gym import GymnasiumEnv
    from rlexp.envs.gym_async import AsyncGymnasiumEnv

    ours, ref = AsyncGymnasiumEnv(env_id, 3), GymnasiumEnv(env_id, 3)
    try:
        ours.set_seed(11), ref.set_seed(11)
        got, want = _resets(ours), _resets(ref)
    finally:
        ours.close(), ref.close()
    for k, (a, b) in enumerate(zip(got, want, strict=True)):
        assert torch.equal(a, b), f"reset {k}: async {a.tolist()} != in-process {b.tolist()}"
    # Copies 0 and 2 were reset 4 times, copy 1 (left out of the masked reset) 3 times.
    plain = _plain_resets(env_id, 11, 3, [4, 3, 4])
    first, second, masked, last = (x.numpy() for x in got)
    for i in range(3):
        np.testing.assert_array_equal(first[i], plain[i][0])
        np.testing.assert_array_equal(second[i], plain[i][1])
        assert not np.array_equal(first[i], second[i])  # a new episode, not the first again
    for i in (0, 2):
        np.testing.assert_array_equal(masked[i], plain[i][2])
        np.testing.assert_array_equal(last[i], plain[i][3])
    # (copy 1's row of the masked reset is TorchRL's: the input tensordict's, here none)
    np.testing.assert_array_equal(last[1], plain[1][2])


SIGINT_TO_THE_GROUP = """
import os, signal, sys
import torch
if __name__ == "__main__":  # (each worker imports this module)
    from rlexp.envs.gym_async import AsyncGymnasiumEnv
    caught = []
    signal.signal(signal.SIGINT, lambda *a: caught.append(1))  # the trainer's handler, in short
    env = AsyncGymnasiumEnv("Hopper-v5", 2)
    env.reset()
    pids = [p.pid for p in env._vec.processes]
    print(os.getpgrp(), *pids, *[os.getpgid(p) for p in pids], flush=True)
    sys.stdin.readline()  # the test sends SIGINT to this process group, then a line
    for _ in range(5):
        env.step_tensors(torch.zeros(2, 3))
    state = env.env_state()
    print(len(caught), state["kind"], all(p.is_alive() for p in env._vec.processes), flush=True)
    env.close()
"""


def test_a_ctrl_c_to_the_trainers_process_group_does_not_reach_the_workers(tmp_path, children):
    """The script stands for the trainer: it leads a process group (``children``), as a run in a
    terminal's foreground does; SIGINT to that group is handled there, and the workers, each the
    leader of a group of its own, step on and hand over their env state."""
    script = tmp_path / "run.py"
    script.write_text(SIGINT_TO_THE_GROUP)
    env = {**os.environ, "PYTHONPATH": str(REPO / "src")}
    proc = children.popen(
        [sys.executable, str(script)], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
        stderr=subprocess.PIPE, text=True, env=env,
    )  # fmt: skip
    group, *rest = (int(x) for x in proc.stdout.readline().split())
    workers, groups = rest[:2], rest[2:]
    assert group == proc.pid and len(workers) == 2
    assert groups == workers, f"worker process groups {groups}: not their own ({workers})"
    os.killpg(proc.pid, signal.SIGINT)
    out, err = proc.communicate("go\n", timeout=120)
    assert proc.returncode == 0, err[-3000:]
    assert out.split() == ["1", "mujoco", "True"], (out, err[-3000:])
