"""The off-policy setting's presets (`cdjax.protocol.Preset`): dataclass defaults < preset < command-line flags.
Without --preset, the preset named like the env is used.

The locomotion presets take the shape of Brax SAC's runs on MJX (128 parallel envs feeding a buffer of about a
million transitions, batches of 512, 8 gradient steps per batched env step, random actions for the first 8192 env
steps) at the issue's budget of 1M env steps; they have not been measured on a GPU yet. `point` and `pendulum` are
small CPU tasks for tests and smoke runs.
"""

from __future__ import annotations

from cdjax.protocol import Preset


def _locomotion(env: str, *, gamma: float = 0.99, reward_scale: float = 1.0, steps: int = 1_000_000) -> Preset:
    return Preset(
        about=f"{steps / 1e6:g}M env steps per run, 128 envs, 8 gradient steps per env step, batch 512",
        config=dict(env=env, num_envs=128, steps_per_update=8, updates_per_step=8, buffer_steps=8192, batch_size=512,
                    learning_starts=8192, n_step=3, horizon=3, episode_length=1000),
        hparams=dict(gamma=(gamma,), reward_scale=(reward_scale,)),
        sweep=dict(total_env_steps=steps, seeds=5))


PRESETS = {
    "ant": _locomotion("ant"),
    "humanoid": _locomotion("humanoid"),
    "halfcheetah": _locomotion("halfcheetah"),
    "hopper": _locomotion("hopper"),
    "point": Preset(
        about="the point mass on a CPU: 16 envs, 20k env steps, small networks",
        config=dict(env="point", num_envs=16, steps_per_update=4, updates_per_step=1, buffer_steps=1024,
                    batch_size=128, learning_starts=512, n_step=3, horizon=3, episode_length=100,
                    actor_hidden=(64, 64), critic_hidden=(64, 64), encoder_hidden=(64,), model_hidden=(64,),
                    latent_dim=32, cc_dim=32),
        hparams=dict(gamma=(0.95,), lr_actor=(1e-3,), lr_critic=(1e-3,), lr_model=(1e-3,)),
        sweep=dict(total_env_steps=20_000, seeds=2, eval_episodes=4)),
    "pendulum": Preset(
        about="Brax's inverted pendulum: 32 envs, 100k env steps",
        config=dict(env="inverted_pendulum", num_envs=32, steps_per_update=4, updates_per_step=1, buffer_steps=4096,
                    batch_size=256, learning_starts=2048, episode_length=1000),
        hparams=dict(gamma=(0.99,)),
        sweep=dict(total_env_steps=100_000, seeds=3)),
}
