"""GPU probe used on 2026-11-21 (H200): CD settings at the Brax-matched config, and 1-seed ant curves.

    python experiments/gpu_probe.py tp          # -> $OUT/tp80.json
    python experiments/gpu_probe.py learn 120   # -> $OUT/ant_learning.json
"""
import json, os, sys, time
import jax, numpy as np
jax.config.update("jax_compilation_cache_dir", "/tmp/jc")
from cdjax import Config, HParams, make_trainer
out = os.environ.get("OUT", "/tmp")
part = sys.argv[1]
def timed(cfg, hp, n=4):
    tr = make_trainer(cfg)
    st = jax.jit(tr.init)(jax.random.key(0), hp)
    t0 = time.perf_counter(); up = jax.jit(tr.update).lower(st, hp).compile(); c = time.perf_counter() - t0
    st, m = up(st, hp); jax.block_until_ready(m)
    ts = []
    for _ in range(n):
        t0 = time.perf_counter(); st, m = up(st, hp); jax.block_until_ready(m); ts.append(time.perf_counter() - t0)
    med = sorted(ts)[len(ts)//2]
    return dict(compile_s=round(c,1), update_s=round(med,3), sps=round(cfg.env_steps_per_update/med))
if part == "tp":
    base = dict(env="ant", num_envs=4096, rollout_len=80, horizon=20, num_epochs=8, num_minibatches=32,
                policy_hidden=(32,32,32,32), value_hidden=(256,)*5)
    cases = {"model-free": dict(arm="model-free"), "mbmf": dict(arm="mbmf"),
             "cd-w2-unroll": dict(cc_windows=2, cc_unroll=20),
             "cd-w2-unroll-ep1": dict(cc_windows=2, cc_unroll=20, cc_epochs=1),
             "cd-w4-unroll-ep2": dict(cc_windows=4, cc_unroll=20, cc_epochs=2)}
    rows = {}
    for name, o in cases.items():
        rows[name] = timed(Config(**base, **o), HParams(alpha=0.0 if name=="mbmf" else 1.0))
        print(name, rows[name], flush=True)
    json.dump(rows, open(f"{out}/tp80.json", "w"), indent=1)
else:
    curves = {}
    for name, o, a in (("model-free", dict(arm="model-free"), 0.0), ("mbmf", dict(arm="mbmf"), 0.0),
                       ("cd", dict(cc_windows=2, cc_unroll=20, cc_epochs=1), 1.0)):
        cfg = Config(env="ant", num_envs=4096, rollout_len=32, horizon=20, num_epochs=4, num_minibatches=32, **o)
        tr = make_trainer(cfg); hp = HParams(alpha=a, reward_scale=1.0, ent_coef=1e-3)
        st = jax.jit(tr.init)(jax.random.key(1), hp); up = jax.jit(tr.update)
        t0 = time.perf_counter(); ms = []
        for i in range(int(sys.argv[2])):
            st, m = up(st, hp); ms.append({k: float(v) for k, v in m.items()})
        jax.block_until_ready(st.params)
        curves[name] = ms
        sel = lambda k: [round(x[k], 3) for x in ms[::10]]
        print(name, round(time.perf_counter()-t0,1), "s; return", sel("episode/return"), "olk", sel("model/openloop_mse_k") if "model/openloop_mse_k" in ms[0] else "", "ol50", sel("model/openloop_mse_50") if "model/openloop_mse_50" in ms[0] else "", flush=True)
    json.dump(curves, open(f"{out}/ant_learning.json", "w"))
