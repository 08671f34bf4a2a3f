"""The settings wear one face: the same role modules, the same public names, and `make_train(config)` that
runs a whole (tiny) run on a CPU and gives a state of the Config's shapes and the setting's metric names;
`cdjax.agents.make_train` dispatches on the Config's type."""

import dataclasses
import importlib

import jax
import numpy as np
import pytest

from cdjax import agents
from cdjax.agents.atari import AtariConfig, AtariHParams
from cdjax.agents.offpolicy import Config as OffPolicyConfig
from cdjax.protocol import ConfigError

from _shared import PIXEL_HP, PIXEL_TINY, POINT

SETTINGS = ("obs", "pixel", "atari", "offpolicy")
ROLES = ("config", "learner", "networks", "losses", "presets")
FACE = ("Config", "HParams", "TrainState", "make_train", "make_trainer", "PRESETS", "SETTING")
UPDATES = 2
TINY = {
    # 6 updates: the program test_train.py's vmap test and test_runner.py run alone (the compilation cache serves it)
    "obs": (POINT.replace(num_updates=6), None),
    "pixel": (PIXEL_TINY.replace(num_updates=UPDATES), PIXEL_HP),
    "atari": (AtariConfig(env="breakout", arm="a2c-cd", num_envs=4, rollout_len=8, horizon=4, conv_channels=4,
                          latent=16, model_hidden=16, encoder_dim=8, episode_length=100, num_updates=UPDATES),
              AtariHParams(lr=3e-3)),
    # the l2 consistency encoder, as PIXEL_TINY's: the paper-cd update with the smallest program to compile (the
    # grounded GRU's is test_offpolicy.py's)
    "offpolicy": (OffPolicyConfig(env="point", num_envs=4, steps_per_update=4, buffer_steps=32, batch_size=8,
                                  learning_starts=12, num_updates=UPDATES, actor_hidden=(16,), critic_hidden=(16,),
                                  encoder_hidden=(16,), model_hidden=(16,), latent_dim=8, cc_encoder="l2",
                                  episode_length=20), None),
}


@pytest.mark.parametrize("name", SETTINGS)
def test_each_setting_has_the_role_modules_and_the_public_names(name):
    package = importlib.import_module(f"cdjax.agents.{name}")
    for role in ROLES:
        importlib.import_module(f"cdjax.agents.{name}.{role}")
    assert set(FACE) <= set(package.__all__), set(FACE) - set(package.__all__)
    config_module = importlib.import_module(f"cdjax.agents.{name}.config")
    learner = importlib.import_module(f"cdjax.agents.{name}.learner")
    presets = importlib.import_module(f"cdjax.agents.{name}.presets")
    # the names are the role modules' own, and the registry's setting is the package's
    assert package.Config is config_module.Config and package.HParams is config_module.HParams
    assert package.make_train is learner.make_train and package.make_trainer is learner.make_trainer
    assert package.TrainState is learner.TrainState and package.PRESETS is presets.PRESETS
    assert agents.get(name) is package.SETTING and package.SETTING.config_type is package.Config
    assert package.SETTING.hparams_type is package.HParams and package.SETTING.make_train is package.make_train
    fields = {field.name for field in dataclasses.fields(package.Config)}
    for name, preset in package.PRESETS.items():  # every preset sets fields of the setting's Config
        assert set(preset.config) <= fields, (name, set(preset.config) - fields)


@pytest.mark.parametrize("name", SETTINGS)
def test_make_train_runs_a_tiny_run_with_the_configs_shapes_and_the_settings_metrics(name):
    package = importlib.import_module(f"cdjax.agents.{name}")
    config, hp = TINY[name]
    hp = package.HParams() if hp is None else hp
    arm = "paper-cd" if name == "offpolicy" else package.SETTING.default_arms[-1]  # an arm with the paper's term
    config = package.SETTING.arm_config(arm, config)
    train = agents.make_train(config)  # the registry's dispatch on the Config's type
    state, metrics = jax.jit(train)(jax.random.key(0), hp)
    assert isinstance(state, package.TrainState)
    expected = jax.eval_shape(package.make_trainer(config).init, jax.random.key(0), hp)
    assert jax.tree.structure(state) == jax.tree.structure(expected)
    for got, want in zip(jax.tree.leaves(state), jax.tree.leaves(expected)):
        assert (got.shape, got.dtype) == (want.shape, want.dtype)
    m = package.SETTING.metrics
    # every panel's metric, but the self-predictive term's, which only the offpolicy setting's self-pred arm has
    names = {m.ret, m.discounted_ret, m.skipped, "loss/consistency"} | {panel[0] for panel in m.panels}
    names -= {"loss/self_predictive"}
    assert names <= set(metrics), names - set(metrics)
    for key, value in metrics.items():
        assert value.shape[0] == config.num_updates, key  # one row per update, scalars inside the scan
    assert np.isfinite(np.asarray(metrics["loss/consistency"])).all()


def test_make_train_dispatch_refuses_what_is_no_settings_config():
    with pytest.raises(ConfigError, match="no setting's Config"):
        agents.make_train({"env": "ant"})
    assert agents.make_trainer(TINY["atari"][0]).config == TINY["atari"][0]
