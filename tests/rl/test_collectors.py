"""The environment under TorchRL's collectors and ParallelEnv (2 workers at most)."""

import functools
import multiprocessing as mp
import signal

import pytest
import torch
from torchrl.collectors import Collector, MultiSyncCollector
from torchrl.envs import ParallelEnv

from hrn_pyg.rl.env import HRNEnv

#: Seconds a collector test may take before it is failed (a hung worker must not hang CI).
TIMEOUT_S = 60

make_env = functools.partial(HRNEnv, "cube_push", batch_size=2, seed=0)


@pytest.fixture(autouse=True)
def _timeout():
    def fail(signum, frame):
        raise TimeoutError(f"collector test ran past {TIMEOUT_S} s")

    previous = signal.signal(signal.SIGALRM, fail)
    signal.alarm(TIMEOUT_S)
    yield
    signal.alarm(0)
    signal.signal(signal.SIGALRM, previous)


@pytest.fixture
def fork_start():
    """Workers forked, not spawned: a spawned worker re-imports torch and TorchRL (~5 s each)."""
    previous = mp.get_start_method(allow_none=True)
    mp.set_start_method("fork", force=True)
    yield
    mp.set_start_method(previous, force=True)


def _check(batch, frames):
    assert batch.numel() == frames
    assert torch.isfinite(batch["next", "observation"]).all()
    t = batch["next", "t"]
    assert (t >= 1).all() and (t <= 10).all()


class RateTaggedDynamics:
    """Cubes at rest 5 m from any goal; every step records the dropout rate it was called with
    and writes it into the next state (cube 1's z velocity), so each collected frame names the
    rate it was stepped at."""

    num_objects, object_dim, state_dim = 2, 6, 12

    def __init__(self):
        self.rates: list[float] = []

    def reset_states(self, batch, generator):
        s = torch.zeros(batch, 2, 6)
        s[:, :, 0] = 5.0
        return s.reshape(batch, 12)

    def roots(self, states):
        return states.reshape(*states.shape[:-1], 2, 6)

    def sample_next(self, states, forces, k, rate, generator):
        self.rates.append(rate)
        out = states[:, None].repeat(1, k, 1)
        out[..., 11] = rate
        return out


def test_sync_collector_collects_and_sees_rate_changes():
    dyn = RateTaggedDynamics()
    env = HRNEnv("cube_push", dyn, batch_size=2, seed=0, dropout_rate=0.3)
    collector = Collector(env, None, frames_per_batch=24, total_frames=48,
                          auto_register_policy_transforms=False)
    try:
        batches = []
        for i, batch in enumerate(collector):
            batches.append(batch)
            env.dropout_rate = 0.0  # a schedule between updates reaches the collected env
        assert len(batches) == 2
        for b in batches:
            _check(b, 24)
        # 12 steps of 2 environments per batch: the dynamics got 0.3 for the first batch's
        # steps and 0.0 for every step after the change, and the frames say the same
        assert collector.env.dynamics is dyn
        assert dyn.rates == [0.3] * 12 + [0.0] * 12
        tagged = [b["next", "observation"][..., 11] for b in batches]
        assert torch.equal(tagged[0], torch.full_like(tagged[0], 0.3))
        assert torch.equal(tagged[1], torch.zeros_like(tagged[1]))
    finally:
        collector.shutdown()


def test_multisync_collector_two_workers(fork_start):
    collector = MultiSyncCollector([make_env, make_env], None, frames_per_batch=24,
                                   total_frames=24, auto_register_policy_transforms=False)
    try:
        batches = list(collector)
        assert len(batches) == 1
        _check(batches[0], 24)
    finally:
        collector.shutdown()


#: what a collected frame is made of: compared key by key between runs
FRAME_KEYS = ("observation", "state", "goal", "action", ("next", "observation"), ("next", "state"),
              ("next", "reward"), ("next", "done"), ("next", "terminated"), ("next", "t"))


def _fixed_policy(env):
    """A deterministic policy of the observation (a fixed random linear map, squashed into the
    force bounds): its actions differ exactly when the observations do."""
    spec = env.action_spec
    obs_dim = env.observation_spec["observation"].shape[-1]
    weight = torch.randn(obs_dim, spec.shape[-1], generator=torch.Generator().manual_seed(0))
    high = spec.space.high

    def policy(td):
        return td.set("action", torch.tanh(td["observation"] @ weight) * high)

    return policy


def _seeded_rollout(seed: int, steps: int = 12):
    env = ParallelEnv(2, make_env, mp_start_method="fork")
    try:
        env.set_seed(seed)
        return env.rollout(steps, policy=_fixed_policy(env), break_when_any_done=False)
    finally:
        env.close()


def _collected(seed: int, global_seed: int, frames: int = 24):
    """One batch of a single-process Collector over ``HRNEnv(seed=seed)``, torch's global
    generator seeded ``global_seed`` first (the environment's seed alone must decide)."""
    env = HRNEnv("cube_push", batch_size=2, seed=seed)
    torch.manual_seed(global_seed)
    collector = Collector(env, _fixed_policy(env), frames_per_batch=frames, total_frames=frames,
                          auto_register_policy_transforms=False)
    try:
        (batch,) = list(collector)
        return batch
    finally:
        collector.shutdown()


def _assert_same_frames(a, b, what):
    for key in FRAME_KEYS:
        assert torch.equal(a[key], b[key]), f"{what}: {key} differs"


def _assert_other_frames(a, b, what):
    for key in ("observation", "action", ("next", "observation")):
        assert not torch.equal(a[key], b[key]), f"{what}: the same {key}"


def test_parallel_env_two_workers_rollout_and_seed():
    """The seed governs the whole collection: the same seed gives the same frames
    (observations, actions, rewards, ...) bit for bit, another seed other ones; in a
    ``ParallelEnv`` (``set_seed``) the two workers of one seed are not copies of each other, and
    in a single-process Collector the environment's own seed decides, whatever the state of
    torch's global generator."""
    td = _seeded_rollout(7)
    assert td.shape == (2, 2, 12)
    assert torch.isfinite(td["next", "state"]).all()
    assert td["next", "done"].any()
    again, other = _seeded_rollout(7), _seeded_rollout(8)
    _assert_same_frames(td, again, "ParallelEnv, seed 7 twice")
    _assert_other_frames(td, other, "ParallelEnv, seeds 7 and 8")
    _assert_other_frames(td[0], td[1], "ParallelEnv, seed 7: the two workers")

    batch = _collected(7, global_seed=1)
    assert batch.numel() == 24 and batch["next", "done"].any()
    _assert_same_frames(batch, _collected(7, global_seed=2), "Collector, seed 7 twice")
    _assert_other_frames(batch, _collected(8, global_seed=1), "Collector, seeds 7 and 8")
