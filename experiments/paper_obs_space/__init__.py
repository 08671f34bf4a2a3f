"""The paper's observation-space setting (Sodhani et al., 2019, section 5.1): Mb-Mf vs Mb-Mf + consistency.

Tasks Ant, Humanoid, Half-Cheetah, Swimmer; arms model-free, Mb-Mf (alpha = 0, with the model-based phase
of Nagabandi et al.), CD with k = 5 and k = 20; 10 seeds vmapped per arm. One command per part:

    python -m experiments.paper_obs_space train --task ant --out runs/paper/ant      # one task, all arms
    python -m experiments.paper_obs_space figure returns --runs runs/paper           # figure: Mb-Mf vs CD k=20
    python -m experiments.paper_obs_space figure k-ablation --runs runs/paper        # figure: k ablation
    python -m experiments.paper_obs_space report --runs runs/paper                   # both figures + RESULTS.md

`train` is `cdjax sweep --preset paper-<task>` (cdjax/agents/obs/presets.py holds every setting) plus a record of
the machine; any further `cdjax sweep` option passes through (e.g. `--steps`, `--seeds`).
"""

TASKS = ("ant", "humanoid", "halfcheetah", "swimmer")
ARMS = ("model-free", "mbmf", "cd-k5", "cd-k20")
ABLATION_TASKS = ("ant", "humanoid")  # the paper's k ablation (with the model-free arm)
