import json, numpy as np
from scipy import stats
rng = np.random.default_rng(0)
def at(path, steps):
    return {r["seed"]: r["eval_return"] for r in map(json.loads, open(path)) if r["env_steps"] == steps}
for steps in (1966080, 2949120):
    a, b = at("levels/level4/rows.jsonl", steps), at("levels/level1/rows.jsonl", steps)
    seeds = sorted(a)
    x, y = np.array([a[s] for s in seeds]), np.array([b[s] for s in seeds])
    boot = lambda v: np.percentile([stats.trim_mean(rng.choice(v, v.size), 0.25) for _ in range(5000)], [2.5, 97.5])
    d = y - x
    print(f"{steps:,} env steps, {len(seeds)} seeds: level 4 IQM {stats.trim_mean(x, .25):.1f} {np.round(boot(x), 1)}, "
          f"level 1 IQM {stats.trim_mean(y, .25):.1f} {np.round(boot(y), 1)}; per seed level 1 - level 4: median {np.median(d):.1f}, "
          f"mean {d.mean():.1f}; Wilcoxon p = {stats.wilcoxon(d).pvalue:.2f}")
