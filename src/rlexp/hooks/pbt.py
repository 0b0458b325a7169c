"""The ``pbt`` hook: Population Based Training (Jaderberg et al. 2017) as each member of a sweep
runs it, at its ready points (docs/pbt.md).

A ready point is the first checkpoint at or past each multiple of ``ready_every`` env steps
(``conf/sweep/pbt.yaml`` sets ``trainer.save_every`` to it). There the member publishes that
checkpoint and its score (``rlexp.pbt.population``), reads its siblings' (async: their newest;
sync: this generation's, waiting for them up to ``sync_timeout_s``), and, when it ranks in the
bottom quantile, copies the training state of a member drawn from the top quantile
(``HookControl.load_state``, applied at the end of the iteration) and perturbs or resamples the
copied hyperparameters (``HookControl.set``, applied after the load). Every decision is appended
to ``<run_dir>/pbt/lineage.jsonl``, which is also part of the hook's checkpointed state: a resumed
member rewrites the file from its checkpoint, so the two never disagree, and continues with the
hyperparameters its checkpoint holds, not the sweep's initial ones.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path
from typing import Any

from rlexp.files.fsutil import atomic_write_text
from rlexp.hooks.base import HookControl, HookState, register_hook
from rlexp.pbt import population as pop
from rlexp.pbt.config import PARAMS, PBTConfig

log = logging.getLogger(__name__)


@register_hook("pbt", points=("train_start", "log", "eval_end", "checkpoint"), params=PARAMS)
class PopulationBasedTraining:
    """One member's side of PBT (params: ``rlexp.pbt.config.PBTConfig``)."""

    def __init__(self, **params: Any) -> None:
        self.cfg = PBTConfig.from_params(params)
        self.last_ready = 0  # env step of the last ready point handled
        self.score: float | None = None  # the latest value of the score (checkpointed with it)
        self.lineage: list[dict[str, Any]] = []  # start, exploit records (pbt/lineage.jsonl)
        self._names: list[str] | None = None  # the members' dir names (the sweep's jobs)
        self._named: set[str] = set()  # strays and damaged files already warned about

    @staticmethod
    def check_params(params: dict[str, Any], where: str) -> None:
        PBTConfig.from_params(params, where)

    def __call__(self, state: HookState, control: HookControl) -> None:
        if state.rank != 0:  # rank 0 decides; its decisions reach every rank
            return
        if state.point in ("log", "eval_end") and (state.point == "eval_end") == (
            self.cfg.score.startswith("eval/")
        ):
            self.score = _score(state, self.cfg.score)
        elif state.point == "train_start":
            self._start(state, control)
        elif state.point == "checkpoint" and self._due(state.global_step, state.total_steps):
            self._ready(state, control, state.checkpoint)

    # -- the points ----------------------------------------------------------------------------------
    def _due(self, step: int, total: int) -> bool:
        every = self.cfg.ready_every
        return step < total and step // every > self.last_ready // every

    def _start(self, state: HookState, control: HookControl) -> None:
        if not self.lineage:  # a new member (or a checkpoint from before PBT)
            values = dict(state.hyperparameters)
            missing = [n for n in self.cfg.hyperparameters if n not in values]
            if missing:
                control.set(missing[0], 0.0)  # raises, naming the mutable ones
            rng = pop.decision_rng(self.cfg.seed, state.run_dir.name, 0)
            start = pop.initial(values, self.cfg, rng)
            for name, value in start.items():
                if value != values[name]:
                    control.set(name, value)
            self.last_ready = state.global_step
            self.lineage.append(
                {
                    "event": "start",
                    "step": state.global_step,
                    "member": state.run_dir.name,
                    "hyperparameters": start,
                }  # fmt: skip
            )
        self._write_lineage(state.run_dir)
        if state.resumed and self._due(state.global_step, state.total_steps):
            # stopped right after its ready checkpoint: that ready point was never decided
            mine = [p for p in _step_checkpoints(state.run_dir) if _step_of(p) == state.global_step]
            if mine:
                self._ready(state, control, mine[-1])

    def _ready(self, state: HookState, control: HookControl, checkpoint: Path | None) -> None:
        cfg, step, run_dir = self.cfg, state.global_step, state.run_dir
        self.last_ready = step
        if checkpoint is None:
            return
        member, generation = run_dir.name, step // cfg.ready_every
        score = self.score
        own = {name: float(state.hyperparameters[name]) for name in cfg.hyperparameters}
        me = pop.Ready(member, step, generation, score, pop.ready_name(step),
                       dict(state.hyperparameters), time.time())  # fmt: skip
        pop.publish(run_dir, checkpoint, me, cfg.keep_ready)
        names = self._members(run_dir)
        if cfg.mode == "sync":
            t0 = time.monotonic()
            others, dropped = pop.wait_for_generation(
                run_dir, names, generation, cfg.sync_timeout_s
            )
            if dropped:
                log.warning(
                    "[pbt] generation %d (step %d): dropped %s after waiting %.0f s "
                    "(hooks.pbt.params.sync_timeout_s=%g); going on with %d of %d members",
                    generation, step, ", ".join(dropped), time.monotonic() - t0,
                    cfg.sync_timeout_s, len(others) + 1, cfg.population_size,
                )  # fmt: skip
        else:
            others = pop.population(run_dir, names, None)
        self._warn_damaged(run_dir)
        rng = pop.decision_rng(cfg.seed, member, generation)
        chosen = pop.choose_source(me, others, cfg, rng)
        if chosen is None:
            log.info(
                "[pbt] step %d: score %s; %d members seen; kept",
                step,
                _shown(score),
                len(others) + 1,
            )
            return
        taken = self._take(run_dir, *chosen, checkpoint)
        if taken is None:
            return
        incoming, source, source_step, copied = taken
        base = {**own, **{k: v for k, v in copied.items() if k in own}}
        new, how = pop.explore(base, cfg, rng)
        control.load_state(incoming)
        for name in cfg.hyperparameters:
            control.set(name, new[name])
        record = {
            "event": "exploit", "step": step, "generation": generation, "member": member,
            "score": score, "source": source.member, "source_step": source_step,
            "source_score": source.score, "old": own, "copied": base, "new": new, "explore": how,
        }  # fmt: skip
        self.lineage.append(record)
        self._write_lineage(run_dir)
        log.info(
            "[pbt] step %d: score %.4g in the bottom quantile: copies member %s (step %d, score "
            "%.4g); %s", step, score, source.member, source_step, source.score,
            ", ".join(f"{k} {own[k]:.4g} -> {new[k]:.4g} ({how[k]})" for k in new),
        )  # fmt: skip

    def _members(self, run_dir: Path) -> list[str]:
        """The population's dir names (read once), and one warning naming any new stray."""
        if self._names is None:
            self._names = pop.job_names(run_dir.parent, self.cfg.population_size)
            if run_dir.name not in self._names:
                log.warning("[pbt] this run's dir %s is not one of the sweep's jobs %s",
                            run_dir.name, ", ".join(self._names))  # fmt: skip
        _, strays = pop.scan(run_dir.parent, self._names)
        pop.name_strays(strays, self._named)
        return self._names

    def _warn_damaged(self, run_dir: Path) -> None:
        """One warning per sibling whose ready.jsonl has lines left out (damaged, wrong types)."""
        for name in self._names or []:
            if name == run_dir.name or f"ready:{name}" in self._named:
                continue
            problems: list[str] = []
            pop.read_ready(run_dir.parent / name, problems)
            if problems:
                self._named.add(f"ready:{name}")
                log.warning("[pbt] member %s: %s (left out)", name, "; ".join(problems[:3]))

    def _take(
        self, run_dir: Path, source_dir: Path, source: pop.Ready, own: Path
    ) -> tuple[Path, pop.Ready, int, dict[str, float]] | None:
        """The source's snapshot, linked into this run's ``pbt/incoming.pt`` and checked against
        this member's own checkpoint ``own`` (same env, algorithm and policy tensors); None
        (logged) when it cannot be had or does not fit: skipped like an unreadable one."""
        from rlexp.checkpoints.files import load_checkpoint_file
        from rlexp.pbt.exploit import misfit

        incoming = run_dir / pop.PBT_DIR / pop.INCOMING
        if not pop.take(source_dir, source, incoming):
            newer = pop.read_ready(source_dir)  # it moved on: its newest, never an older one
            source = newer[-1] if newer else source
            if not newer or not pop.take(source_dir, source, incoming):
                log.warning("[pbt] member %s's ready snapshot is gone; no exploit", source.member)
                return None
        try:
            ckpt = load_checkpoint_file(incoming, "resume")
        except (ValueError, OSError) as exc:
            log.warning("[pbt] member %s's snapshot cannot be used (%s); no exploit",
                        source.member, exc)  # fmt: skip
            return None
        step = int(ckpt["global_step"])
        if step < source.step:
            log.warning("[pbt] member %s's snapshot is of step %d, older than its ready point %d; "
                        "no exploit", source.member, step, source.step)  # fmt: skip
            return None
        hps = ckpt["algorithm"].get("hyperparameters") or {}
        why = pop.hyperparameter_values(hps) or misfit(ckpt, own)
        if why:
            log.warning("[pbt] member %s's snapshot does not fit this member (%s); no exploit",
                        source.member, why)  # fmt: skip
            return None
        return incoming, source, step, {str(k): float(v) for k, v in hps.items()}

    # -- lineage and state ---------------------------------------------------------------------------
    def _write_lineage(self, run_dir: Path) -> None:
        path = run_dir / pop.PBT_DIR / pop.LINEAGE
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(path, "".join(json.dumps(r) + "\n" for r in self.lineage))

    def state_dict(self) -> dict[str, Any]:
        return {
            "last_ready": self.last_ready,
            "score": self.score,
            "lineage": json.dumps(self.lineage),
        }

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        self.last_ready = int(sd["last_ready"])
        self.score = None if sd.get("score") is None else float(sd["score"])
        self.lineage = list(json.loads(sd["lineage"]))


def _score(state: HookState, key: str) -> float | None:
    """The member's score now: its own recent returns (training metrics), or an eval metric."""
    import math

    source = state.eval_metrics if key.startswith("eval/") else state.metrics
    value = source.get(key)
    return float(value) if value is not None and math.isfinite(float(value)) else None


def _step_checkpoints(run_dir: Path) -> list[Path]:
    from rlexp.checkpoints.files import step_checkpoints

    return step_checkpoints(run_dir / "checkpoints")


def _step_of(path: Path) -> int:
    return int(path.stem.rsplit("_step_", 1)[1])


def _shown(score: float | None) -> str:
    return "none yet" if score is None else f"{score:.4g}"
