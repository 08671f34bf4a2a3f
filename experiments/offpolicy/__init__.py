"""Does consistency help a sample-efficient learner? (issue 69; the plan: PLAN.md)

The off-policy setting (cdjax.agents.offpolicy) on the MJX locomotion tasks at 1M env steps, 10 seeds per arm: SAC
(model-free), SAC with a latent model (model), and the model with the paper's consistency (paper-cd) or with the
self-predictive form of TD-MPC2, SPR and MR.Q (self-pred), each consistency arm at two weights (alpha, vmapped with
the seeds) and two horizons. Every run logs the diagnostics (Config.diagnostics, which change no training number).

    python -m experiments.offpolicy list                    # the units
    python -m experiments.offpolicy run UNIT --out DIR      # one unit on a GPU
    python -m experiments.offpolicy.report                  # RESULTS.md from data/ (CPU)
"""

TASKS = ("ant", "humanoid", "halfcheetah", "hopper")
ARMS = ("model-free", "model", "paper-cd", "self-pred")
SEEDS = 10
STEPS = 1_000_000
ALPHAS = (0.1, 1.0)  # the consistency arms' weights, a grid vmapped with the seeds
HORIZONS = (3, 5)
