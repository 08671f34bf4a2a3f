"""Configs and compiled functions shared between test modules (MJX compiles slowly on CPU)."""

import functools
import pathlib

import jax
import pytest

from cdjax import io

from cdjax import Config, HParams, make_agent, make_trainer
from cdjax.agents.pixel import PRESETS as PIXEL_PRESETS, PixelConfig, PixelHParams

POINT = Config(env="point", num_envs=16, rollout_len=12, horizon=4, num_updates=3, num_epochs=2,
               num_minibatches=2, episode_length=40, policy_hidden=(16,), value_hidden=(16,),
               model_hidden=(32,), encoder_dim=8, eval_horizon=10, eval_envs=4)

# One small MJX task for integration: learning, compile-once and the NaN guard share its compiled update.
PENDULUM = Config(env="inverted_pendulum", num_envs=32, rollout_len=32, horizon=8, num_updates=1, num_epochs=4,
                  num_minibatches=4, episode_length=200, policy_hidden=(64, 64), value_hidden=(64, 64),
                  model_hidden=(64,), encoder_dim=32, eval_horizon=50, eval_envs=4)
PENDULUM_HP = HParams(alpha=1.0, lr_policy=1e-3, lr_value=1e-3)


# For the few tests whose programs run long enough that executing them costs more than compiling them (learning runs,
# MPC on MJX): XLA's default optimisation level instead of the test session's 0 (tests/conftest.py).
OPTIMISED = {"xla_backend_optimization_level": 3}
# For the programs that a test compares bit for bit with another program (or with JAX's op-by-op execution): XLA:CPU's
# own fusion emitters, which users' programs get, instead of the test session's older ones (tests/conftest.py), whose
# fusions round a few operations differently from one program to the next.
EXACT = {"xla_cpu_use_fusion_emitters": True}


@functools.lru_cache(maxsize=None)
def compiled(config: Config, optimised: bool = False):
    """(agent, jit(init), jit(update)) for a config, built once per test session; `optimised`: the update compiled
    at OPTIMISED's level (for a config whose update one test runs many times)."""
    agent = make_agent(config)
    return agent, jax.jit(agent.init), jax.jit(agent.update, compiler_options=OPTIMISED if optimised else None)


@functools.lru_cache(maxsize=None)
def host_trainer(config: Config):
    """The observation-space agent of a config as the host side sees it (cdjax.protocol.Trainer)."""
    return make_trainer(config)


# The pixel setting's tiny model (tests/test_pixel_model.py, tests/_sharded_pixel_sweep.py): ltq-cd with the l2
# encoder (the whole update with the smallest program to compile) and two convolutions instead of four.
PIXEL_TINY = PixelConfig(**PIXEL_PRESETS["pixel-tiny"].config, arm="ltq-cd", encoder="l2").replace(conv_layers=2)
PIXEL_HP = PixelHParams(lr=3e-3, imitation_coef=100.0)  # imitation weighed against the summed ELBO


@functools.lru_cache(maxsize=None)
def pixel_programs():
    """(learner, jit(init), jit(update), traced) of PIXEL_TINY on synthetic frames, built once per test session
    (tests/test_pixel_model.py and tests/test_sweep.py share them); traced["count"]: update's traces."""
    from cdjax.agents.pixel.learner import PixelLearner
    from cdjax.agents.pixel.synthetic import SyntheticWorld

    learner = PixelLearner(PIXEL_TINY, world=SyntheticWorld(PIXEL_TINY))
    traced = {"count": 0}

    def counted(state, hp):
        traced["count"] += 1
        return learner.update(state, hp)

    return learner, jax.jit(learner.init), jax.jit(counted), traced


# The point-mass config POINT on the command line, with 2 seeds and 2 updates (of 192 env steps) per chunk.
TINY_ARGS = ["--env", "point", "--num-envs", "16", "--rollout-len", "12", "--horizon", "4", "--num-epochs", "2",
             "--num-minibatches", "2", "--episode-length", "40", "--policy-hidden", "16", "--value-hidden", "16",
             "--model-hidden", "32", "--encoder-dim", "8", "--eval-horizon", "10", "--eval-envs", "4",
             "--seeds", "2", "--chunk-updates", "2", "--no-progress"]


def fail_in_one_sentence(capsys, main, argv) -> str:
    """Run main(argv), which must exit with status 2 after one `cdjax: ...` sentence on stderr; return it."""
    with pytest.raises(SystemExit) as info:
        main(argv)
    err = capsys.readouterr().err
    assert info.value.code == 2, err
    assert "Traceback" not in err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("cdjax: ") and lines[0].endswith("."), err
    return lines[0]


def benchmark_refuses(capsys, main, argv, prog: str, said: str) -> str:
    """Run a benchmark's main(argv), which must exit with status 2 after one line `python -m benchmarks.PROG: ...` on
    stderr that holds `said`; return that line."""
    capsys.readouterr()
    with pytest.raises(SystemExit) as stop:
        main(argv)
    out, err = capsys.readouterr()
    assert stop.value.code == 2 and err.count("\n") == 1, err
    assert err.startswith(f"python -m benchmarks.{prog}: ") and said in err, err
    return err.strip()


def logged_rows(run_dir, name: str = "metrics.jsonl") -> list[dict]:
    """A JSONL log of a run without the wall-clock (the only field that differs between two runs), in a fixed
    order (arms that resume from different updates interleave their chunks differently)."""
    rows = [{k: v for k, v in row.items() if k not in ("wall_s", "phase_wall_s")}
            for row in io.read_jsonl(pathlib.Path(run_dir) / name)]
    return sorted(rows, key=lambda r: (r["arm"], r["hp"], r["seed"], r.get("update", -1), r.get("deterministic", 0)))


def ended(procs, timeout: float = 600) -> list[tuple[int, str, str]]:
    """(exit status, stdout, stderr) of each subprocess.Popen once it has ended; any still running after `timeout`
    seconds is killed (and the test fails on communicate's TimeoutExpired)."""
    try:
        said = [p.communicate(timeout=timeout) for p in procs]
        return [(p.returncode, *outputs) for p, outputs in zip(procs, said)]
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
