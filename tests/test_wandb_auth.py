"""W&B's "is there a key" is wandb's own answer, for the server it talks to (#30 item 14): a
self-hosted server (WANDB_BASE_URL) with its key in ~/.netrc runs online, a key for another host
does not count."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from conftest import REPO

KEY = "k" * 40
PROBE = (
    "import logging, sys; logging.basicConfig(stream=sys.stderr, format='%(message)s');"
    "from rlexp.run.metrics import _wandb_mode; print(_wandb_mode('auto'))"
)


def _mode(home, **env_extra) -> subprocess.CompletedProcess:
    env = {
        k: v for k, v in os.environ.items()
        if not k.startswith("WANDB_") and k not in ("NETRC", "HOME", "XDG_CONFIG_HOME")
    }  # fmt: skip
    env.update(HOME=str(home), PYTHONPATH=str(REPO / "src"), **env_extra)
    return subprocess.run(
        [sys.executable, "-c", PROBE], capture_output=True, text=True, timeout=120, env=env
    )


def _netrc(home, host: str) -> None:
    (home / ".netrc").write_text(f"machine {host}\n  login user\n  password {KEY}\n")
    (home / ".netrc").chmod(0o600)


@pytest.mark.parametrize(
    ("netrc_host", "base_url", "api_key", "mode"),
    [
        ("wandb.example.com", "https://wandb.example.com", None, "online"),  # self-hosted
        ("api.wandb.ai", "https://wandb.example.com", None, "offline"),  # a key for another host
        (None, "https://wandb.example.com", KEY, "online"),  # WANDB_API_KEY
        (None, None, None, "offline"),
    ],
)
def test_auto_mode_asks_wandb_for_the_servers_credentials(
    tmp_path, netrc_host, base_url, api_key, mode
):
    if netrc_host:
        _netrc(tmp_path, netrc_host)
    extra = {"WANDB_BASE_URL": base_url} if base_url else {}
    if api_key:
        extra["WANDB_API_KEY"] = api_key
    out = _mode(tmp_path, **extra)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split()[-1] == mode
    warned = [line for line in out.stderr.splitlines() if line.startswith("W&B: no API key")]
    if mode == "offline":
        assert len(warned) == 1 and (base_url or "https://") in warned[0]
    else:
        assert not warned, out.stderr
