"""The first pass's observers stepped a block at a time (service/observer_process.py): the inline numbers."""

from __future__ import annotations

import math

import numpy as np

from magcomp.adapters.config import Config
from magcomp.service.estimators import ThetaEstimator
from magcomp.service.observer_process import BlockObservers

Call = tuple[int, tuple[tuple[float, ...], tuple[float, ...], float, float] | None]


def _calls(seed: int, n: int) -> list[Call]:
    """A seeded stream of two compasses' observer calls: a hand rotation at varying throttle, with resets."""
    rng = np.random.default_rng(seed)
    theta = np.array([40.0, -25.0, 60.0])
    out: list[Call] = []
    for k in range(n):
        idx = k % 2
        if k % 97 == 50:
            out.append((idx, None))
            continue
        t = 0.02 * k
        w = (math.sin(t), 0.7 * math.cos(1.3 * t), 0.4 * math.sin(0.7 * t))
        thr = 0.5 + 0.3 * math.sin(0.2 * t)
        v = np.array([200.0 * math.cos(t), 200.0 * math.sin(t), 400.0]) + theta * thr * thr
        v += rng.normal(0.0, 1.0, 3)
        out.append((idx, (w, tuple(v.tolist()), thr, 0.02)))
    return out


def test_block_observers_give_the_inline_numbers_bit_for_bit() -> None:
    cfg = Config()
    inline = [ThetaEstimator(cfg, np.zeros(3)), ThetaEstimator(cfg, np.array([5.0, 0.0, -5.0]))]
    owner = BlockObservers(block=7)  # blocks that end mid-stream, on either compass
    deferred = [owner.estimator(0, cfg, np.zeros(3)), owner.estimator(1, cfg, np.array([5.0, 0.0, -5.0]))]
    infos = [None, None]
    for idx, args in _calls(3, 1500):
        if args is None:
            inline[idx].reset_filters()
            deferred[idx].reset_filters()
        else:
            infos[idx] = inline[idx].step(*args)  # type: ignore[call-overload]
            deferred[idx].step(*args)
    deferred[0].sync()
    for idx in (0, 1):
        assert deferred[idx].local.state == inline[idx].state
        assert deferred[idx].local.converged == inline[idx].converged
        assert deferred[idx].last_info == infos[idx]
    assert np.linalg.norm(np.asarray(inline[0].theta_values())) > 1.0  # it moved: not a vacuous match


def test_calls_wait_until_a_block_is_full_or_someone_reads() -> None:
    cfg = Config()
    owner = BlockObservers(block=1000)
    obs = owner.estimator(0, cfg, None)
    start = obs.local.state
    for _, args in _calls(4, 200)[::2]:
        if args is not None:
            obs.step(*args)
    assert obs.local.state is start and obs.last_info is None  # nothing run yet
    obs.sync()
    assert obs.local.state is not start and obs.last_info is not None
