"""The observation-space setting's presets: named sets of explicit overrides of the Config, HParams and sweep
defaults (`cdjax.protocol.Preset`).

Precedence (cdjax sweep): dataclass defaults < preset < flags given on the command line. Without
`--preset`, the preset named like the env (if any) is used, so `cdjax sweep --env ant` gets the ant
settings.

The per-environment settings start from Brax's published PPO settings for the same MJX tasks
(discount, reward scaling, entropy cost, clipping 0.3, epochs, minibatches, parallel envs, budget), with
the rollout long enough to hold the paper's k-step windows (k = 20 for the locomotion tasks as in the
paper, k = 5 for the manipulation tasks) and the consistency term on a few windows per sequence in the
first epoch (every window in every epoch, the paper's schedule, cost about 1.5x Mb-Mf's update with the fused term
as measured in benchmarks/; the presets switch to it when that cost drops, or when it learns better).
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


def _paper(env: str, *, steps: int, mpc_horizon: int, mpc_candidates: int, mpc_reward: str = "true") -> Preset:
    """The paper's observation-space setting (experiments/paper_obs_space, which runs it as units: PLAN.md there).

    PPO, the model and the consistency term at the task's own preset above (Brax's PPO settings; the learner is
    at parity with Brax's PPO on ant and halfcheetah), with staggered resets (each env starts at its own point of
    the time limit: its first, shortened episode is not logged) and the arms model-free, Mb-Mf and CD with k = 5
    and k = 20, 10 seeds vmapped. The consistency term is on the preset's cheap schedule (the first epoch only);
    the experiment's units add the paper's weights (--cc-policy 1) and the paper's schedule (--cc-epochs 0).

    The Mb-Mf phase (every arm with a model, before PPO; its env steps are charged to the budget) is Nagabandi et
    al.'s with what mattered for it to hand PPO a policy better than random actions (measured on halfcheetah:
    experiments/paper_obs_space/PLAN.md): 64 envs per seed, 500 random steps, 4 rounds of 250 MPC steps with
    1024 candidates scored by the task's reward of the predicted observations (humanoid: the model's reward; see
    cdjax/envs/rewards.py), the MPC acting with the mean first action of its 32 best candidates (the best one's is
    mostly noise), 90% of every model minibatch from the MPC data once there is some, 3 deterministic DAgger
    rounds of 100 steps, and 4 x 100 steps of checks of the policy handed to PPO against an untrained one.
    """
    base = PRESETS[env]
    return Preset(
        about=f"paper, obs-space: {env}, model-free/mbmf/cd-k5/cd-k20 x 10 seeds, {steps / 1e6:g}M env steps, "
              "Mb-Mf phase, staggered resets",
        config={**base.config, "stagger_resets": True},
        hparams={**base.hparams, "alpha": (1.0,)},
        sweep=dict(arms=("model-free", "mbmf", "cd-k5", "cd-k20"), seeds=10, total_env_steps=steps, eval_episodes=10),
        phase=dict(num_envs=64, random_steps=500, aggregation_iters=4, mpc_steps_per_iter=250, model_epochs=30,
                   model_minibatch=512, onpolicy_fraction=0.9, mpc_horizon=mpc_horizon,
                   mpc_candidates=mpc_candidates, mpc_reward=mpc_reward, mpc_elites=32, distill_iters=3,
                   distill_steps_per_iter=100, dagger_deterministic=True, distill_epochs=100, distill_minibatch=512,
                   value_epochs=10, relabel_chunk=128, handover_steps=100),
    )


# Nagabandi et al.'s MPC: ant horizon 5 (15,000 candidates), cheetah horizon 20 (1,000); here 1,024 (2,048 for ant).
# Budgets: experiments/paper_obs_space/PLAN.md (the units pass --steps; these are the same numbers).
PRESETS.update({
    "paper-ant": _paper("ant", steps=50_000_000, mpc_horizon=5, mpc_candidates=2048),
    "paper-humanoid": _paper("humanoid", steps=10_000_000, mpc_horizon=5, mpc_candidates=1024, mpc_reward="model"),
    "paper-halfcheetah": _paper("halfcheetah", steps=10_000_000, mpc_horizon=20, mpc_candidates=1024),
    "paper-swimmer": _paper("swimmer", steps=5_000_000, mpc_horizon=20, mpc_candidates=1024),
})


def get(name: str) -> Preset:
    if name not in PRESETS:
        raise ConfigError(f"Unknown preset {name!r}; choose one of: {', '.join(PRESETS)}.")
    return PRESETS[name]
