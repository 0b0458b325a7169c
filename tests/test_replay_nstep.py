"""n-step returns in the replay buffer against a hand-written loop: per env, never across an
episode's end (a termination stops the bootstrap, a truncation ends the sum and bootstraps from
its next observation), windows completed by a later batch, and across a save/load."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from rlexp.algorithms.replay import Replay

N, GAMMA = 3, 0.8
E, T = 2, 9
# env 0: terminated at t=2, truncated at t=6; env 1: truncated at t=1, terminated at t=3 and t=4
TERM = {(0, 2), (1, 3), (1, 4)}
TRUNC = {(0, 6), (1, 1)}


def rollout() -> TensorDict:
    """obs = 100*env + t (so a row names its step), rewards distinct per step."""
    t = torch.arange(T, dtype=torch.float32)
    obs = torch.stack([100 * e + t for e in range(E)])  # [E, T]
    term = torch.zeros(E, T, 1, dtype=torch.bool)
    trunc = torch.zeros(E, T, 1, dtype=torch.bool)
    for e, s in TERM:
        term[e, s] = True
    for e, s in TRUNC:
        trunc[e, s] = True
    reward = (torch.arange(E * T, dtype=torch.float32).reshape(E, T, 1) * 0.37 + 1.0) ** 1.3
    return TensorDict(
        {
            "observation": obs[..., None].expand(E, T, 4).clone(),
            "action": obs[..., None].expand(E, T, 2).clone() * -1,
            "next": {
                "observation": obs[..., None].expand(E, T, 4).clone() + 0.5,
                "reward": reward,
                "terminated": term,
                "truncated": trunc,
            },
        },
        [E, T],
    )


def expected(td: TensorDict) -> dict[tuple[int, int], tuple]:
    """The hand-written n-step transitions: (env, t) -> (R, next obs id, term, trunc, steps)."""
    out = {}
    r = td["next", "reward"][..., 0]
    for e in range(E):
        for t in range(T):
            total, k = 0.0, 0
            while True:
                total += GAMMA**k * float(r[e, t + k])
                end = (e, t + k)
                if end in TERM or end in TRUNC or k == N - 1:
                    out[(e, t)] = (total, 100 * e + t + k + 0.5, end in TERM, end in TRUNC, k + 1)
                    break
                k += 1
                if t + k >= T:  # the window runs past the data: not yet a transition
                    break
    return out


def contents(replay: Replay) -> dict[tuple[int, int], tuple]:
    rows = replay._rb.storage.get(torch.arange(len(replay)))
    out = {}
    for i in range(len(replay)):
        ident = int(rows["observation"][i, 0])
        assert int(rows["action"][i, 0]) == -ident
        out[(ident // 100, ident % 100)] = (
            float(rows["next", "reward"][i, 0]),
            float(rows["next", "observation"][i, 0]),
            bool(rows["next", "terminated"][i, 0]),
            bool(rows["next", "truncated"][i, 0]),
            int(rows["steps_to_next_obs"][i, 0]),
        )
        assert bool(rows["next", "done"][i, 0]) == (
            out[(ident // 100, ident % 100)][2:4] != (False, False)
        )
    assert len(out) == len(replay), "a transition was stored twice"
    return out


def assert_same(got: dict, want: dict) -> None:
    assert sorted(got) == sorted(want)
    for key, w in want.items():
        g = got[key]
        assert abs(g[0] - w[0]) <= 1e-5 * max(1.0, abs(w[0])), (key, g, w)
        assert g[1:] == w[1:], (key, g, w)


def test_nstep_matches_a_hand_loop_across_episode_ends_and_batches():
    td = rollout()
    want = expected(td)
    # the literal cases the loop must agree with, worked out by hand
    r = td["next", "reward"][..., 0]
    assert want[(0, 1)][2:] == (True, False, 2)  # window cut by the termination at t=2
    assert want[(0, 4)][1:] == (6.5, False, True, 3)  # the truncation at t=6 is bootstrapped from
    assert want[(0, 5)][1:] == (6.5, False, True, 2)  # cut by it: the sum ends, still bootstrapped
    assert want[(1, 0)][1:] == (101.5, False, True, 2)
    assert want[(1, 2)][1:] == (103.5, True, False, 2)
    assert want[(1, 4)][1:] == (104.5, True, False, 1)
    assert abs(want[(0, 3)][0] - (r[0, 3] + 0.8 * r[0, 4] + 0.64 * r[0, 5])) < 1e-4
    assert (0, 7) not in want and (1, 8) not in want  # windows not complete at the data's end
    replay = Replay(64, n_step=N, gamma=GAMMA, seed=1)
    for lo, hi in ((0, 2), (2, 5), (5, T)):  # windows span batches; an episode ends in each
        replay.extend(td[:, lo:hi])
    assert_same(contents(replay), want)


@pytest.mark.parametrize("split", [5, 1])  # 1: nothing stored yet, only waiting steps
def test_nstep_state_survives_a_save_and_load(tmp_path, split):
    td = rollout()
    first = Replay(64, directory=tmp_path, n_step=N, gamma=GAMMA, seed=1)
    first.extend(td[:, :split])
    assert len(first) == (0 if split == 1 else 8)  # env 0: t=0-2; env 1: t=0-4
    state = first.save("a")
    second = Replay(64, directory=tmp_path, n_step=N, gamma=GAMMA, seed=1)
    second.load_state_dict(state)
    second.extend(td[:, split:])
    assert_same(contents(second), expected(td))


def test_nstep_one_is_the_plain_transition():
    td = rollout()
    replay = Replay(64, seed=0)
    replay.extend(td)
    rows = replay._rb.storage.get(torch.arange(len(replay)))
    assert len(replay) == E * T and "steps_to_next_obs" not in rows.keys()
    assert torch.equal(rows["next", "reward"], td["next", "reward"].reshape(-1, 1))
    assert torch.equal(rows["next", "truncated"], td["next", "truncated"].reshape(-1, 1))


def test_a_bad_waiting_step_in_the_manifest_is_one_line(tmp_path):
    from rlexp.algorithms.replay_files import ReplayFileError

    replay = Replay(64, directory=tmp_path, n_step=N, gamma=GAMMA)
    replay.extend(rollout()[:, :4])
    state = replay.save()
    bad_obs = {**state["pending"]["steps"], "observation": torch.zeros(E, N - 1, 5)}
    for pending, says in [
        ({**state["pending"], "valid": state["pending"]["valid"].int()}, "pending.valid"),
        ({**state["pending"], "steps": bad_obs}, "pending.steps.observation is not torch.float32"),
        ({"valid": torch.ones(E, N, dtype=torch.bool), "steps": {}}, "holds 3 steps; n_step=3"),
    ]:
        with pytest.raises(ReplayFileError) as err:
            Replay(64, directory=tmp_path, n_step=N, gamma=GAMMA).load_state_dict(
                {**state, "pending": pending}
            )
        assert says in str(err.value) and "\n" not in str(err.value), str(err.value)
