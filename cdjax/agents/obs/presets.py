"""The observation-space setting's presets: named sets of explicit overrides of the Config, HParams and sweep
defaults (`cdjax.protocol.Preset`).

Precedence (cdjax sweep): dataclass defaults < preset < flags given on the command line. Without
`--preset`, the preset named like the env (if any) is used, so `cdjax sweep --env ant` gets the ant
settings.

The per-environment settings start from Brax's published PPO settings for the same MJX tasks
(discount, reward scaling, entropy cost, clipping 0.3, epochs, minibatches, parallel envs, budget), with
the rollout long enough to hold the paper's k-step windows (k = 20 for the locomotion tasks as in the
paper, k = 5 for the manipulation tasks) and the consistency term on a few windows per sequence in the
first epoch (every window in every epoch, the paper's schedule, costs 1.52x Mb-Mf's update with the fused term:
benchmarks/results/2026-11-24-h100-compare; the presets switch to it at 1.5x, or when it learns better).
Only ant and halfcheetah have been measured on a GPU with these settings (benchmarks/LEARNING.md). `cpu-smoke` was
measured: `cdjax sweep --preset cpu-smoke --out runs/smoke` took 126 s end to end on a shared 2-core
CPU with an empty compilation cache (setup 32 s, compile 31 s, training 35 s, evaluation 18 s).
"""

from __future__ import annotations

from cdjax.protocol import ConfigError, Preset


def _locomotion(env: str, *, steps: int, gamma: float, reward_scale: float, ent_coef: float, num_epochs: int,
                num_envs: int = 2048, horizon: int = 20, rollout_len: int = 32, segment_len: int = 0,
                num_minibatches: int = 32, action_repeat: int = 1, episode_length: int = 1000,
                cc_windows: int = 4, cc_epochs: int = 1, networks: dict | None = None, about: str = "") -> Preset:
    """Brax's PPO settings for a task; the consistency term on `cc_windows` windows per sequence in the first
    `cc_epochs` epochs (0: all), its k-step scan unrolled."""
    return Preset(
        about=about or f"{steps / 1e6:g}M env steps per run, {num_envs} envs x T={rollout_len}, k={horizon}",
        config=dict(env=env, num_envs=num_envs, rollout_len=rollout_len, segment_len=segment_len, horizon=horizon,
                    num_epochs=num_epochs, num_minibatches=num_minibatches, episode_length=episode_length,
                    action_repeat=action_repeat, cc_windows=cc_windows, cc_epochs=cc_epochs, cc_unroll=horizon,
                    **(networks or {})),
        hparams=dict(gamma=(gamma,), reward_scale=(reward_scale,), ent_coef=(ent_coef,), clip_eps=(0.3,)),
        sweep=dict(total_env_steps=steps, seeds=3),
    )


BRAX_NETWORKS = dict(policy_hidden=(32,) * 4, value_hidden=(256,) * 5)  # Brax PPO's default network sizes

PRESETS: dict[str, Preset] = {
    # ant and halfcheetah: the structure measured against Brax PPO in benchmarks/LEARNING.md (sequences of 20
    # steps, as Brax's unrolls), the consistency term on each sequence's window in the first epoch.
    "ant": _locomotion("ant", steps=50_000_000, gamma=0.97, reward_scale=10.0, ent_coef=1e-2, num_epochs=4,
                       rollout_len=80, segment_len=20, cc_windows=0, networks=BRAX_NETWORKS),
    "humanoid": _locomotion("humanoid", steps=50_000_000, gamma=0.97, reward_scale=0.1, ent_coef=1e-3, num_epochs=8),
    "halfcheetah": _locomotion("halfcheetah", steps=50_000_000, gamma=0.95, reward_scale=1.0, ent_coef=1e-3,
                               num_epochs=8, rollout_len=160, segment_len=20, cc_windows=0, networks=BRAX_NETWORKS),
    "hopper": _locomotion("hopper", steps=20_000_000, gamma=0.97, reward_scale=1.0, ent_coef=1e-3, num_epochs=4),
    "walker2d": _locomotion("walker2d", steps=20_000_000, gamma=0.97, reward_scale=1.0, ent_coef=1e-3, num_epochs=4),
    "swimmer": _locomotion("swimmer", steps=20_000_000, gamma=0.995, reward_scale=1.0, ent_coef=1e-3, num_epochs=4),
    "reacher": _locomotion("reacher", steps=50_000_000, gamma=0.95, reward_scale=5.0, ent_coef=1e-3, num_epochs=8,
                           horizon=5, rollout_len=50, action_repeat=4),
    "pusher": _locomotion("pusher", steps=50_000_000, gamma=0.95, reward_scale=5.0, ent_coef=1e-2, num_epochs=8,
                          horizon=5, rollout_len=32, num_minibatches=16),
    "inverted_pendulum": _locomotion("inverted_pendulum", steps=2_000_000, gamma=0.97, reward_scale=10.0,
                                     ent_coef=1e-2, num_epochs=4, horizon=8),
    # Finishes on a 2-core CPU in about 2 minutes, compile included, and the return clearly rises
    # (untrained ~7, after 100 updates ~180 of at most 200 in both arms).
    "cpu-smoke": Preset(
        about="2-core CPU in a few minutes: MJX inverted pendulum, mbmf vs cd (alpha=1), 3 seeds",
        config=dict(env="inverted_pendulum", num_envs=32, rollout_len=32, horizon=8, num_epochs=4,
                    num_minibatches=4, episode_length=200, policy_hidden=(64, 64), value_hidden=(64, 64),
                    model_hidden=(64,), encoder_dim=32, eval_horizon=50, eval_envs=4),
        hparams=dict(alpha=(1.0,), lr_policy=(1e-3,), lr_value=(1e-3,)),
        sweep=dict(arms=("mbmf", "cd"), seeds=3, total_env_steps=100 * 32 * 32, chunk_updates=10, eval_episodes=10),
    ),
    # Plumbing: the pure-JAX point mass, compiles in seconds (for trying the command and for tests).
    "point": Preset(
        about="pure-JAX point mass, tiny, seconds on a CPU (plumbing)",
        config=dict(env="point", num_envs=32, rollout_len=16, horizon=4, num_epochs=2, num_minibatches=2,
                    episode_length=50, policy_hidden=(32,), value_hidden=(32,), model_hidden=(32,), encoder_dim=16,
                    eval_horizon=10, eval_envs=4),
        hparams=dict(lr_policy=(1e-3,), lr_value=(1e-3,)),
        sweep=dict(seeds=2, total_env_steps=40 * 32 * 16, chunk_updates=10, eval_episodes=4),
    ),
}


def _paper(env: str, *, steps: int, gamma: float, reward_scale: float, ent_coef: float, mpc_horizon: int,
           mpc_candidates: int) -> Preset:
    """The paper's observation-space setting (experiments/paper_obs_space) at a budget one GPU session affords.

    The policy is Nagabandi et al.'s distilled policy: a 64 x 64 tanh MLP.

    Arms model-free, Mb-Mf (alpha = 0) and CD with k = 5 and k = 20, 10 seeds vmapped, 256 envs per seed.
    The Mb-Mf phase (arms with a model) is Nagabandi et al.'s, shrunk: 64 envs, 100 random steps, 2 MPC
    aggregation rounds of 100 steps, 2 DAgger rounds of 50 steps (25,600 env steps per run, charged to
    the budget). Consistency: 4 random windows per env per minibatch, in every epoch, k-step scans
    unrolled 10 (the all-windows schedule costs ~5x; benchmarks/RESULTS.md).
    """
    return Preset(
        about=f"paper, obs-space: {env}, model-free/mbmf/cd-k5/cd-k20 x 10 seeds, {steps / 1e6:g}M env steps, Mb-Mf phase",
        config=dict(env=env, num_envs=256, rollout_len=32, horizon=20, num_epochs=4, num_minibatches=8,
                    episode_length=1000, policy_hidden=(64, 64), activation="tanh", value_hidden=(256, 256),
                    model_hidden=(500,),
                    encoder="gru", encoder_dim=128, cc_windows=4, cc_unroll=10, cc_epochs=0, eval_envs=8),
        hparams=dict(alpha=(1.0,), gamma=(gamma,), reward_scale=(reward_scale,), ent_coef=(ent_coef,)),
        sweep=dict(arms=("model-free", "mbmf", "cd-k5", "cd-k20"), seeds=10, total_env_steps=steps, eval_episodes=10),
        phase=dict(num_envs=64, random_steps=100, aggregation_iters=2, mpc_steps_per_iter=100, model_epochs=20,
                   model_minibatch=512, mpc_horizon=mpc_horizon, mpc_candidates=mpc_candidates, distill_iters=2,
                   distill_steps_per_iter=50, distill_epochs=50, distill_minibatch=512, value_epochs=5,
                   relabel_chunk=256),
    )


# Nagabandi et al.'s MPC: ant horizon 5 (15,000 candidates), cheetah horizon 20 (1,000); here fewer candidates.
PRESETS.update({
    "paper-ant": _paper("ant", steps=2_000_000, gamma=0.97, reward_scale=10.0, ent_coef=1e-2, mpc_horizon=5,
                        mpc_candidates=1024),
    "paper-humanoid": _paper("humanoid", steps=1_000_000, gamma=0.97, reward_scale=0.1, ent_coef=1e-3,
                             mpc_horizon=5, mpc_candidates=1024),
    "paper-halfcheetah": _paper("halfcheetah", steps=500_000, gamma=0.95, reward_scale=1.0, ent_coef=1e-3,
                                mpc_horizon=20, mpc_candidates=256),
    "paper-swimmer": _paper("swimmer", steps=2_000_000, gamma=0.995, reward_scale=1.0, ent_coef=1e-3,
                            mpc_horizon=20, mpc_candidates=256),
})


def get(name: str) -> Preset:
    if name not in PRESETS:
        raise ConfigError(f"Unknown preset {name!r}; choose one of: {', '.join(PRESETS)}.")
    return PRESETS[name]
