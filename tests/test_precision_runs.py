"""``trainer.precision`` through the command line: a float32 run resumed with bf16 continues
(and the run's config records the precision), its checkpoints hold float32 weights, and
``rlexp export`` / ``rlexp eval`` of a bf16 run compute in float32 (what the exported file gives,
bit for bit); a bad value and a recurrent policy are refused in one line, exit 2."""

from __future__ import annotations

import pytest
import torch
import yaml
from test_precision import MatmulDtypes

from conftest import TINY, compose, rlexp_cli, run_train
from rlexp.checkpoints.files import load_checkpoint, step_checkpoints
from rlexp.config.validate import ConfigError, to_root_config


@pytest.fixture(scope="module")
def resumed(tmp_path_factory):
    """A float32 run of 512 env steps, then the same run dir continued to 1024 with bf16."""
    root = tmp_path_factory.mktemp("precision")
    run = root / "run"
    common = [*TINY, f"hydra.run.dir={run}", "trainer.progress=false", "logger=none"]
    run_train(common, cwd=root)
    first = step_checkpoints(run / "checkpoints")[-1]
    out = run_train([*common, "trainer.total_frames=1024", "trainer.precision=bf16"], cwd=root)
    return run, first, out.stdout + out.stderr


def test_a_float32_run_resumes_with_bf16_and_records_it(resumed):
    run, first, log = resumed
    assert f"[resume] continuing from {first}" in log, log
    config = yaml.safe_load((run / "config.yaml").read_text())
    assert config["trainer"]["precision"] == "bf16"
    last = load_checkpoint(run)
    assert last["global_step"] == 1024 and last["config"]["trainer"]["precision"] == "bf16"
    floats = [t for t in last["policy"].values() if t.is_floating_point()]
    assert floats and {t.dtype for t in floats} <= {torch.float32, torch.float64}
    assert any(t.dtype == torch.float32 for t in floats)


def test_export_and_eval_of_a_bf16_run_compute_in_float32(resumed, tmp_path):
    from rlexp.deploy.policy_eval import eval_config, open_source
    from rlexp.envs.factory import make_env
    from rlexp.runtime.precision import set_precision

    run, _, _ = resumed
    rc, out, err = rlexp_cli("export", run, "--format", "torchscript", "--out", tmp_path / "p.pt")
    assert rc == 0, err
    module = torch.jit.load(str(tmp_path / "p.pt"))
    assert {p.dtype for p in module.parameters()} | {b.dtype for b in module.buffers()} <= {
        torch.float32,
        torch.int64,
    }
    source = open_source(run)
    config = to_root_config(eval_config(source.config))
    env = make_env(config.env, 1, seed=0)
    policy = source.build(config, env)  # rlexp eval's deterministic policy
    obs = torch.randn(64, int(env.observation_spec["observation"].shape[-1])) * 2
    env.close()
    net = policy.actor_net
    assert net.autocast_dtype is None, "rlexp eval runs the checkpoint in float32"
    with torch.no_grad(), MatmulDtypes() as seen:
        exported = module(obs)
        loc, _ = net(obs)
    assert seen.dtypes() == {torch.float32}
    assert torch.equal(exported, loc), "the export is the float32 policy, bit for bit"
    set_precision(policy, "bf16", "cpu")  # what in-training evaluation runs
    with torch.no_grad():
        mixed, _ = net(obs)
    assert not torch.equal(mixed, loc)
    torch.testing.assert_close(mixed, loc, rtol=0.05, atol=0.05)


def test_an_unknown_precision_is_one_line_exit_2(tmp_path):
    out = run_train(["trainer.precision=bf16-mixed", *TINY], cwd=tmp_path, check=False)
    lines = out.stderr.strip().splitlines()
    assert out.returncode == 2 and "Traceback" not in out.stderr, out.stderr
    assert lines == [
        "config error: trainer.precision='bf16-mixed' must be one of ['fp32', 'bf16'] (bf16: "
        "mixed precision, float32 weights and loss maths, Lightning's 'bf16-mixed'; not with "
        "policy.memory)"
    ], lines
    assert not (tmp_path / "outputs").exists()


def test_a_recurrent_policy_with_bf16_is_refused_in_one_line():
    cfg = compose(["env=gym_cartpole", "policy.memory.type=lstm", "trainer.precision=bf16"])
    with pytest.raises(ConfigError) as err:
        to_root_config(cfg)
    assert str(err.value) == (
        "policy.memory.type=lstm: trainer.precision=bf16, but the recurrent core runs in float32 "
        "only; use trainer.precision=fp32, or policy.memory.type=none"
    )
    assert to_root_config(compose(["env=gym_cartpole", "trainer.precision=bf16"]))


def test_sigkill_and_resume_of_a_bf16_run_is_bit_identical(tmp_path):
    """bf16's kernels are deterministic here: train -> SIGKILL -> resume under bf16 ends with the
    uninterrupted bf16 run's weights, optimiser state, evaluation and best.pt, bit for bit."""
    from test_resume import _assert_resume_is_exact

    _assert_resume_is_exact(
        tmp_path, "hopper", frames=512, batch=256, extra=["trainer.precision=bf16"], eval_every=512
    )
