"""The pixel setting's model, update and sweep (cdjax.agents.pixel) on synthetic frames (no physics: fast to compile;
tests/test_pixels.py renders the real tasks).

The world here (cdjax.agents.pixel.synthetic) is a stand-in for the rendered expert data: frames of noise with a
random brightness, expert actions that are a fixed function of the newest frame's brightness (imitation is
learnable), and a scene whose brightness follows the action for the evaluation episodes. Every test shares one
compiled `update`."""

from __future__ import annotations

import dataclasses
import functools
import json
import math

import imageio.v3 as iio
import jax
import jax.extend.core
import jax.numpy as jnp
import numpy as np
import pytest

from cdjax import ConfigError, agents, io
from cdjax.agents import pixel
from cdjax.agents.pixel import PixelHParams, PixelLearner
from cdjax.agents.pixel.synthetic import SyntheticWorld
from cdjax.cli import main
from cdjax.runner import restore_arms
from experiments.pixel.report import write_strips

from _shared import EXACT, PIXEL_HP, PIXEL_TINY, TINY_ARGS, fail_in_one_sentence, logged_rows, pixel_programs

# ltq-cd with the l2 encoder: the whole update (ELBO, imitation, consistency) with the smallest program to compile;
# the GRU encoders (the default is grounded-gru) are checked in the consistency test.
# Two convolutions instead of four (the model is size-generic): a smaller program to compile.
TINY, HP = PIXEL_TINY, PIXEL_HP
A = 2


def learner_for(config=TINY):
    return PixelLearner(config, world=SyntheticWorld(config))


@pytest.fixture(scope="module")
def learner():
    return pixel_programs()[0]


@pytest.fixture(scope="module")
def traced():
    return pixel_programs()[3]


@pytest.fixture(scope="module")
def update():
    return pixel_programs()[2]


@pytest.fixture(scope="module")
def init():
    return pixel_programs()[1]


@pytest.fixture(scope="module")
def state(init):
    return init(jax.random.key(0), HP)


def test_elbo_of_an_untrained_model_equals_a_hand_computation(learner, state):
    model, c = learner.model, learner.config
    T, B, F = 3, 2, c.frame_stack
    rng = np.random.default_rng(1)  # inputs drawn in numpy: eager jax.random calls would each compile a program
    frames = rng.integers(0, 256, (T + F - 1, B, c.image_size, c.image_size, 3), np.uint8)
    actions = rng.uniform(-1, 1, (T, B, A)).astype(np.float32)
    key_eps = jax.random.key(1)
    params = state.params  # the untrained model of the shared initial state (its own init ran op by op)
    elbo, parts, _ = jax.jit(model.elbo)(params, frames, actions, key_eps)

    eps = np.asarray(jax.random.normal(key_eps, (T, B, c.latent)))
    encode = jax.jit(lambda x: model.encoder.apply(params["encoder"], x))
    prior = jax.jit(lambda h, a: model.core.apply(params["core"], h, a, method="prior"))
    posterior = jax.jit(lambda e, h, a: model.core.apply(params["core"], e, h, a, method="posterior"))
    transition = jax.jit(lambda h, cell, z, a: model.core.apply(params["core"], h, cell, z, a, method="transition"))
    decode = jax.jit(lambda x: model.decoder.apply(params["decoder"], x))
    h = cell = np.zeros((B, c.hidden), np.float32)
    a_prev = np.zeros((B, A), np.float32)
    total = np.zeros(B)
    for t in range(T):
        obs = np.concatenate([frames[t + i] for i in range(F)], -1).astype(np.float32) / 255.0
        e = encode(obs)
        pm, ps = (np.asarray(x, np.float64) for x in prior(h, a_prev))
        qm, qs = (np.asarray(x, np.float64) for x in posterior(e, h, a_prev))
        z = (qm + qs * eps[t]).astype(np.float32)
        h, cell = transition(h, cell, z, a_prev)
        mean, std = (np.asarray(x, np.float64) for x in decode(np.concatenate([h, z], -1)))
        x = frames[t + F - 1].astype(np.float64) / 255.0
        log_p = (-0.5 * ((x - mean) / std) ** 2 - np.log(std) - 0.5 * math.log(2 * math.pi)).sum((1, 2, 3))
        kl = (np.log(ps / qs) + (qs**2 + (qm - pm) ** 2) / (2 * ps**2) - 0.5).sum(-1)
        np.testing.assert_allclose(parts["kl"][t], kl, rtol=1e-4, atol=1e-4)
        total += log_p - kl
        a_prev = actions[t]
    # summed over pixels, latents and steps (about 3 steps x 768 pixel terms here), not averaged
    np.testing.assert_allclose(np.asarray(elbo), total, rtol=1e-5)
    assert abs(total.mean()) > T * c.image_size**2 * 3 * 0.1


def test_open_loop_draws_from_the_prior_and_never_reads_the_frames_it_predicts(learner, state):
    model, c = learner.model, learner.config
    params = state.params
    frames = jnp.swapaxes(state.heldout.frames, 0, 1).astype(jnp.float32)  # [C+K+F-1, M, S, S, 3], differentiable
    actions = jnp.swapaxes(state.heldout.actions, 0, 1)
    read = c.context + c.frame_stack - 1  # frames of the context's observations
    grads = jax.jit(jax.grad(lambda f: model.openloop_loglik(params, f, actions, jax.random.key(2), c.context)[1].sum()))(
        frames)
    assert np.all(np.asarray(grads[read:]) == 0.0)  # the predicted frames: exactly no influence
    assert np.abs(np.asarray(grads[:read])).sum() > 0  # the context: read

    B = 3
    rng = np.random.default_rng(3)  # numpy: eager jax.random calls would each compile a program
    h0, c0 = (rng.standard_normal((B, c.hidden), np.float32) for _ in range(2))
    acts = rng.uniform(-1, 1, (4, B, A)).astype(np.float32)
    eps = rng.standard_normal((4, B, c.latent), np.float32)
    h_im, _, z_im = jax.jit(model.imagine)(params, h0, c0, acts, eps)
    prior = jax.jit(lambda h, a: model.core.apply(params["core"], h, a, method="prior"))
    transition = jax.jit(lambda h, cell, z, a: model.core.apply(params["core"], h, cell, z, a, method="transition"))
    h, cell = h0, c0
    for t in range(4):  # z_t = prior mean + prior std * eps_t, then the transition
        mean, std = prior(h, acts[t])
        np.testing.assert_allclose(z_im[t], mean + std * eps[t], rtol=1e-5, atol=1e-5)
        h, cell = transition(h, cell, mean + std * eps[t], acts[t])
        np.testing.assert_allclose(h_im[t], h, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("encoder,imagine", [("grounded-gru", "policy"), ("gru", "expert"), ("l2", "policy")])
def test_consistency_is_zero_when_the_two_pathways_coincide(encoder, imagine):
    config = TINY.replace(encoder=encoder, imagine_actions=imagine)
    learner = learner_for(config)
    model = learner.model
    params = model.init(jax.random.key(7))
    L, B, H = 6, 3, config.hidden
    actions = jax.random.uniform(jax.random.key(8), (L, B, A), minval=-1, maxval=1)
    eps = jax.random.normal(jax.random.key(9), (L - 1, B, config.latent))
    h0 = jax.random.normal(jax.random.key(10), (B, H))
    c0 = jax.random.normal(jax.random.key(11), (B, H))
    policy = (lambda h: model.act(params, h)) if imagine == "policy" else None
    h, cell, _ = model.imagine(params, h0, c0, None if policy else actions[:-1], eps, policy=policy)
    # a "closed loop" that is itself the open loop under the same noise: every window imagines it exactly
    states = jnp.concatenate([jnp.concatenate([h0, c0], -1)[None], jnp.concatenate([h, cell], -1)])
    offsets = jnp.arange(L - 1 - config.horizon + 1)
    terms = jax.jit(learner.consistency_terms)
    same, _ = terms(params, states, actions, eps, offsets, HP)
    np.testing.assert_allclose(float(same["consistency"]), 0.0, atol=1e-6)
    moved, _ = terms(params, states.at[1:].add(0.1), actions, eps, offsets, HP)
    assert float(moved["consistency"]) > 1e-3


@pytest.mark.parametrize("encoder,imagine", [("grounded-gru", "policy"), ("gru", "expert"), ("frozen-gru", "policy")])
def test_the_fused_chain_is_the_scanned_terms_with_their_gradients_on_each_path(encoder, imagine):
    """core_impl fused runs the consistency term's k steps and both encodings by `chain.pixel_chain` (its backward
    written out): its terms, metrics and the gradients of a random mix of them (every parameter, the closed loop's
    states and the actions) equal the scanned path's (core_impl flax) to float32 rounding, with the model's and the
    policy's paths scaled (cc_model 0.7, cc_policy 0.3) and the real rows' encoder unscaled for grounded-gru."""
    from cdjax.agents.pixel import chain

    config = TINY.replace(encoder=encoder, imagine_actions=imagine, horizon=3)
    learners = [learner_for(config), learner_for(config.replace(core_impl="fused"))]
    params = learners[0].model.init(jax.random.key(7))
    L, B, H = 7, 3, config.hidden
    actions = jax.random.uniform(jax.random.key(8), (L, B, A), minval=-1, maxval=1)
    eps = jax.random.normal(jax.random.key(9), (L - 1, B, config.latent))
    states = jax.random.normal(jax.random.key(10), (L, B, 2 * H))
    offsets = jnp.array([0, 2, 3])
    hp = HP.replace(cc_model=0.7, cc_policy=0.3)
    mix = {"consistency": 1.3, "encoder_aux": -0.6}

    def scalar(lrn, params, states, actions):
        terms, _ = lrn.consistency_terms(params, states, actions, eps, offsets, hp)
        return sum(mix[name] * value for name, value in terms.items())

    def terms_and_grads(lrn, params, states, actions):  # one compiled program per path (op by op, the first case
        # compiled some 500 small programs)
        return (lrn.consistency_terms(params, states, actions, eps, offsets, hp),
                jax.grad(functools.partial(scalar, lrn), argnums=(0, 1, 2))(params, states, actions))

    calls = []
    original = chain._chain_fwd
    try:
        chain._chain_fwd = lambda *a: calls.append(1) or original(*a)  # noqa: E731 - count the chain's traces
        results, grads = zip(*(jax.jit(functools.partial(terms_and_grads, lrn))(params, states, actions)
                               for lrn in learners))
    finally:
        chain._chain_fwd = original
    assert calls, "the fused learner did not run the chain"
    (terms, metrics), (terms_f, metrics_f) = results
    assert set(terms) == set(terms_f) and set(metrics) == set(metrics_f)
    for name in terms:
        np.testing.assert_allclose(terms_f[name], terms[name], rtol=1e-5, err_msg=name)
    for name in metrics:
        np.testing.assert_allclose(metrics_f[name], metrics[name], rtol=1e-5, atol=1e-7, err_msg=name)
    assert float(terms["consistency"]) > 1e-3
    reached = {"core", "policy", "cc_encoder"} - ({"cc_encoder"} if encoder == "frozen-gru" else set()) - (
        {"policy"} if imagine == "expert" else set())
    for group in params:  # the term reaches the core, the policy (when it acts) and the encoder (unless frozen)
        largest = [max(float(np.abs(np.asarray(x)).max()) for x in jax.tree.leaves(g[0][group])) for g in grads]
        assert (largest[0] > 0) == (group in reached), (group, largest)
        if group in reached:
            assert relative(grads[1][0][group], grads[0][0][group]) < 1e-5, group
        else:
            assert largest[1] == 0, group
    for i, name in ((1, "states"), (2, "actions")):
        np.testing.assert_allclose(grads[1][i], grads[0][i], rtol=1e-4, atol=1e-6, err_msg=name)


def test_the_update_compiles_once_and_imitation_loss_falls(state, update, traced):
    losses = []
    for _ in range(240):
        state, metrics = update(state, HP)
        losses.append(float(metrics["loss/imitation"]))
    assert traced["count"] == 1
    assert np.isfinite(losses).all()
    assert np.mean(losses[-20:]) < 0.7 * np.mean(losses[:20]), losses[::20]
    for name in ("heldout/loglik_k", "heldout/loglik_50", "heldout/imitation", "loss/consistency", "model/elbo_per_frame"):
        assert np.isfinite(float(metrics[name])), name


def _producers_until_barrier(jaxpr, var) -> set[str]:
    """The primitives that compute `var` in `jaxpr` (the outer one: calls are not entered), walking back from it and
    stopping at an optimization_barrier."""
    producer = {out: eqn for eqn in jaxpr.eqns for out in eqn.outvars}
    seen, found, todo = set(), set(), [var]
    while todo:
        eqn = producer.get(todo.pop())
        if eqn is None or id(eqn) in seen:
            continue
        seen.add(id(eqn))
        found.add(eqn.params.get("name") or eqn.primitive.name)
        if eqn.primitive.name != "optimization_barrier":
            todo.extend(v for v in eqn.invars if isinstance(v, jax.extend.core.Var))
    return found


def test_the_batchs_sequence_indices_are_materialised_before_the_frames_gather(learner, state):
    """The batch's indices reach the gather of the kept frames through an optimization_barrier, not straight from
    randint: on a GPU XLA fused the threefry into that gather, recomputing it per gathered element (11.5 of 80 ms
    per update, H100). Dropping the barrier fails this test; the update's values are the same either way."""
    jaxpr = jax.make_jaxpr(learner.update)(state, HP).jaxpr
    frames_shape = state.data.frames.shape
    gathers = [e for e in jaxpr.eqns if e.primitive.name == "gather" and e.invars[0].aval.shape == frames_shape]
    assert len(gathers) == 1, [e.invars[0].aval for e in jaxpr.eqns if e.primitive.name == "gather"]
    producers = _producers_until_barrier(jaxpr, gathers[0].invars[1])
    assert "optimization_barrier" in producers, producers
    assert "_randint" not in producers, producers


@pytest.mark.parametrize("name, arm, horizon", [("ltq", "ltq", 10), ("ltq-cd", "ltq-cd", 10), ("ltq-cd3", "ltq-cd", 3)])
def test_pixel_arm_names_set_the_arm_and_only_ltq_cd_takes_a_horizon_in_its_name(name, arm, horizon):
    config = pixel.arm_config(name, pixel.PixelConfig(horizon=10))
    assert (config.arm, config.horizon) == (arm, horizon)


@pytest.mark.parametrize("name, words", [
    ("ltq5", "Arm 'ltq5': only ltq-cd takes a horizon in its name"),
    ("ltq-cd-5", "Unknown arm 'ltq-cd-5'"), ("ltq-5", "Unknown arm 'ltq-5'"), ("ltqcd", "Unknown arm 'ltqcd'"),
    ("ltq-cd0", "Arm 'ltq-cd0': horizon"),
])
def test_malformed_pixel_arm_names_are_refused_in_one_sentence(capsys, tmp_path, name, words):
    out = tmp_path / "run"
    line = fail_in_one_sentence(capsys, main, ["sweep", "--setting", "pixel", "--preset", "pixel-tiny", "--out", str(out),
                                               "--arms", name])
    assert words in line and not out.exists()


def test_a_sweep_whose_arms_measure_their_return_at_different_horizons_says_so():
    """The pixel return (the summary's ranking) is the likelihood at each arm's own k: `ltq ltq-cd5` under a k = 10
    preset sets likelihoods at 10 and at 5 side by side, which the sweep's note names (and the common measure); arms
    at one k, and the obs setting's env returns, give none."""
    from cdjax.cli import build_parser, sweep_spec
    from cdjax.runner.plan import plan_arms, return_note

    def note(setting, *argv):
        setting = agents.get(setting)
        spec = sweep_spec(build_parser(setting).parse_args(["sweep", "--out", "x", "--setting", setting.name, *argv]),
                          setting)
        return return_note(setting, plan_arms(spec, setting))

    said = note("pixel", "--preset", "pixel-halfcheetah", "--arms", "ltq", "ltq-cd5")
    assert "horizon (ltq 10, ltq-cd5 5)" in said and "heldout/loglik_k" in said and "heldout/loglik_50" in said
    assert note("pixel", "--preset", "pixel-halfcheetah", "--arms", "ltq", "ltq-cd") is None
    assert note("obs", "--preset", "point", "--arms", "cd", "cd-k2") is None


def test_cdjax_plot_keeps_the_note_on_the_arms_return_under_its_summary(tmp_path):
    """The note a sweep of arms at different k gives is in the summary.md that `cdjax plot` writes, computed by
    return_note from run.json's arms: the same text as from the sweep's plans. Pooled runs of one k each (ltq in one,
    ltq-cd5 in the other) set the two measures side by side too; either run alone does not. Hand-written logs."""
    from cdjax.cli import build_parser, sweep_spec
    from cdjax.runner.plan import plan_arms, return_note, run_record

    setting = agents.get("pixel")

    def run(name, *argv):
        spec = sweep_spec(build_parser(setting).parse_args(["sweep", "--out", "x", "--setting", "pixel", "--preset",
                                                            "pixel-halfcheetah", "--seeds", "2", *argv]), setting)
        plans = plan_arms(spec, setting)
        out = tmp_path / name
        out.mkdir()
        (out / "run.json").write_text(json.dumps(run_record(spec, plans, setting)))
        io.append_jsonl(out / "metrics.jsonl", [
            {"arm": plan.name, "hp": plan.labels[0], "seed": s, "update": u, "env_steps": 100 * u,
             "heldout/loglik_k": -10.0 * plan.config.horizon + s + u, "heldout/loglik_50": -500.0 + s + u}
            for plan in plans for s in range(2) for u in range(1, 4)])
        return out, plans

    both, plans = run("both", "--arms", "ltq", "ltq-cd5")
    note = return_note(setting, plans)
    assert note and "horizon (ltq 10, ltq-cd5 5)" in note
    main(["plot", str(both), "--bootstrap-reps", "20"])
    assert note in (both / "summary.md").read_text().splitlines()
    (a, _), (b, _) = run("a", "--arms", "ltq"), run("b", "--arms", "ltq-cd5", "--seed", "1")
    main(["plot", str(a), "--bootstrap-reps", "20"])
    assert "Note: the arms' return" not in (a / "summary.md").read_text()
    main(["plot", str(a), str(b), "--out", str(tmp_path / "pooled"), "--bootstrap-reps", "20"])
    assert note in (tmp_path / "pooled" / "summary.md").read_text().splitlines()


SYNTHETIC = dataclasses.replace(pixel.SETTING, name="pixel-synthetic",
                                make_trainer=lambda config: pixel.trainer_of(learner_for(config)))
agents.register(SYNTHETIC)


def test_a_sweep_through_the_cli_resumes_and_equals_each_seed_alone(tmp_path, learner, init, update, traced):
    """`cdjax sweep` of the pixel setting (on the synthetic world) with a resume in the middle: logs, checkpoints,
    evaluation from pixels, plots; and its 2 seeds, vmapped in compiled chunks, end where each seed's own
    updates (init and `update` of this module, one at a time) end."""
    out = tmp_path / "px"
    flags = ["--setting", "pixel-synthetic", "--preset", "pixel-tiny", "--arms", "ltq-cd", "--encoder", "l2", "--conv-layers", "2", "--lr",
             str(HP.lr), "--imitation-coef", str(HP.imitation_coef), "--bootstrap-reps", "50", "--no-progress"]
    main(["sweep", *flags, "--steps", str(3 * 12), "--no-final-eval", "--out", str(out)])  # 3 updates of 12 frames
    run = json.loads((out / "run.json").read_text())
    assert run["setting"] == "pixel-synthetic" and run["metrics"]["return"] == "heldout/loglik_k"
    main(["sweep", "--out", str(out), "--resume", "--steps", str(6 * 12), "--no-progress"])
    main(["eval", str(out), "--episodes", "2"])  # the imitation policy from frames (the spec has no final eval)
    main(["plot", str(out), "--bootstrap-reps", "50"])
    rows = logged_rows(out)
    assert sorted({r["update"] for r in rows}) == list(range(1, 7)) and len(rows) == 2 * 6  # 2 seeds x 6 updates
    assert all(np.isfinite(r[n]) for r in rows for n in ("heldout/loglik_k", "heldout/loglik_50", "loss/consistency"))
    evals = io.read_jsonl(out / "eval.jsonl")
    assert len(evals) == 2 and all(e["update"] == 6 and e["lengths"] == [3, 3] for e in evals)  # the time-out
    assert (out / "summary.md").exists() and (out / "plots" / "model.png").exists()

    _, (arm,) = restore_arms(out)
    for i in range(2):
        np.testing.assert_allclose(float(arm.hps.lr[i]), HP.lr, rtol=1e-6)
        key = jax.random.wrap_key_data(np.asarray(jax.random.key_data(arm.keys[i])))  # off the sweep's mesh
        alone = init(key, HP)
        for _ in range(6):
            alone, _ = update(alone, HP)
        for a, b in zip(jax.tree.leaves(alone.params), jax.tree.leaves(arm.state.params)):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b)[i], rtol=2e-4, atol=2e-5)
    assert traced["count"] == 1  # the module's update was compiled once for every use

    # the strips as `experiments.pixel.report --strips` draws them from the run directory: seed 0 of each label
    (path,) = write_strips(str(out), str(tmp_path / "strips"), sequences=2)
    assert path.name == "ltq-cd.png"
    c = arm.plan.config
    assert iio.imread(path).shape == (2 * 3 * (c.image_size + 2), (c.context + c.eval_horizon) * (c.image_size + 2), 3)


def test_the_expert_is_the_best_evaluated_policy_of_a_model_free_sweep(tmp_path):
    """export_expert (what the pixel units expert-TASK run after the expert's sweep) on the pure-JAX point
    mass: the saved policy and statistics are the restored ones of the run with the best deterministic evaluation."""
    from cdjax.agents.experts import load_expert
    from cdjax.runner.export_expert import main as export

    run = tmp_path / "expert-run"
    main(["sweep", "--setting", "obs", *TINY_ARGS, "--arms", "model-free", "--steps", "384", "--eval-episodes", "2",
          "--bootstrap-reps", "20", "--out", str(run)])  # the shared tiny point-mass sweep (tests/_shared.py)
    export([str(run), str(tmp_path / "point.msgpack")])
    expert = load_expert(tmp_path / "point.msgpack")
    evals = [e for e in io.read_jsonl(run / "eval.jsonl") if e["deterministic"]]
    best = max(evals, key=lambda e: e["eval/return"])
    assert expert.eval_return == best["eval/return"] and expert.config.env == "point"
    _, (arm,) = restore_arms(run)
    for a, b in zip(jax.tree.leaves(expert.policy), jax.tree.leaves(arm.state.params["policy"])):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b)[best["seed"]])
    np.testing.assert_array_equal(np.asarray(expert.norms.obs.mean), np.asarray(arm.state.norms.obs.mean)[best["seed"]])
    # a file that is no expert: one sentence, not msgpack's or a KeyError's traceback
    (tmp_path / "text.msgpack").write_text("hello")
    blob = (tmp_path / "point.msgpack").read_bytes()
    (tmp_path / "cut.msgpack").write_bytes(blob[: len(blob) // 2])
    for name in ("text", "cut"):
        with pytest.raises(ConfigError, match=rf"^--expert '.*{name}.msgpack' is not an expert file \("):
            load_expert(tmp_path / f"{name}.msgpack")


def test_export_expert_refuses_what_it_cannot_export_in_one_sentence(tmp_path, capsys):
    """python -m cdjax.runner.export_expert: --help shows the usage (exit status 0); a run directory that does
    not exist, an EXPERT_FILE that is a directory, or a wrong number of arguments: one sentence, exit status 2,
    nothing written."""
    from cdjax.runner.export_expert import main as export

    with pytest.raises(SystemExit) as stop:
        export(["--help"])
    assert stop.value.code == 0 and "usage: python -m cdjax.runner.export_expert" in capsys.readouterr().out
    for argv, said in (([str(tmp_path / "none"), str(tmp_path / "e.msgpack")], f"{tmp_path / 'none'} holds no run"),
                       ([str(tmp_path), str(tmp_path)], f"EXPERT_FILE {tmp_path} is a directory"),
                       ([str(tmp_path)], "required: EXPERT_FILE")):
        with pytest.raises(SystemExit) as stop:
            export(argv)
        err = capsys.readouterr().err
        assert stop.value.code == 2 and err.startswith("python -m cdjax.runner.export_expert: ") and said in err
        assert err.count("\n") == 1 and "Traceback" not in err, err
    assert list(tmp_path.iterdir()) == []


def test_subpixel_decoder_layer_rearranges_each_pixels_channels_into_a_2x2_block():
    """depth_to_space: channel (di * 2 + dj) * C + c of input pixel (i, j) lands on pixel (2i + di, 2j + dj),
    channel c; the decoder's two upsampling kinds give the same output shapes."""
    from cdjax.agents.pixel.networks import ConvDecoder, depth_to_space

    x = np.arange(2 * 3 * 4 * 8, dtype=np.float32).reshape(2, 3, 4, 8)  # C = 2 after the 2x2 rearrangement
    y = np.asarray(depth_to_space(jnp.asarray(x)))
    assert y.shape == (2, 6, 8, 2)
    for i, j, di, dj, c in [(0, 0, 0, 0, 0), (1, 2, 1, 0, 1), (2, 3, 1, 1, 0), (2, 1, 0, 1, 1)]:
        assert y[1, 2 * i + di, 2 * j + dj, c] == x[1, i, j, (di * 2 + dj) * 2 + c]
    z = jnp.ones((3, 5))
    shapes = set()
    for kind in ("transpose", "subpixel"):
        dec = ConvDecoder(16, 2, 4, 0.01, kind)
        mean, std = dec.apply(dec.init(jax.random.key(0), z), z)
        shapes.add((mean.shape, std.shape))
        assert float(std.min()) >= 0.01
    assert shapes == {((3, 16, 16, 3), (3, 16, 16, 3))}


# --- precision, convolution arrangements and the policy's rate (cdjax.agents.pixel.convs; issue 22) ----------------

# The metrics compared over 3 updates of the tiny model from the `state` fixture. That the float32 switch is the model
# of before is checked against the layers and the optimiser it was written with (bit for bit, in-process, below),
# not against numbers copied from an older run.
NAMES = ("loss/total", "model/elbo_per_frame", "loss/imitation", "loss/consistency", "heldout/loglik_k",
         "heldout/imitation", "grad/norm")


def three_updates(update, state):
    for _ in range(3):
        state, metrics = update(state, HP)
    return state, {name: float(metrics[name]) for name in NAMES}


def relative(a, b) -> float:
    a, b = (np.concatenate([np.ravel(np.asarray(x, np.float64)) for x in jax.tree.leaves(t)]) for t in (a, b))
    return float(np.linalg.norm(a - b) / np.linalg.norm(b))


@pytest.fixture(scope="module")
def one_batch(state):
    """config -> (loss, gradient, jaxpr) of one batch's loss (the state's first batch_size sequences, key 4) at the
    state's parameters: the value and the gradient from one compiled program per config, its jaxpr from the same
    trace, each config's computed once for the tests below that compare precisions and core implementations."""
    frames, actions = (jnp.swapaxes(x[:TINY.batch_size], 0, 1) for x in (state.data.frames, state.data.actions))
    done = {}

    def of(config):
        if config not in done:
            lrn = learner_for(config)
            loss = lambda p: lrn.loss(p, frames, actions, HP, jax.random.key(4))[0]  # noqa: E731
            traced = jax.jit(jax.value_and_grad(loss)).trace(state.params)
            loss, grads = traced.lower().compile()(state.params)
            done[config] = (float(loss), grads, traced.jaxpr.jaxpr)
        return done[config]

    return of


def test_float32_is_the_default_and_bfloat16_agrees_within_its_rounding(state, update, one_batch):
    """compute_dtype float32 is the default (with conv_impl grouped; the next tests: the model before, bit for bit);
    bfloat16 operands (float32 parameters, optimiser state and ELBO sums), as the presets run them (output_grad
    compute), change every metric of 3 updates by less than 2e-3 relative, and the gradient of the loss of one batch by
    less than 1e-2 (relative L2 per parameter group), with output_grad float32 too. (output_grad changes only the
    output layers' backward, the next test: the loss is the same number and the gradients agree as closely, so the
    update of output_grad float32 is not compiled again here.)"""
    assert (TINY.compute_dtype, TINY.conv_impl, HP.lr_policy) == ("float32", "grouped", 0.0)
    _, metrics = three_updates(update, state)
    assert all(np.isfinite(v) for v in metrics.values()), metrics
    mixed = TINY.replace(compute_dtype="bfloat16")
    assert jax.tree.structure(jax.eval_shape(learner_for(mixed).model.init, jax.random.key(0))) == jax.tree.structure(
        state.params)
    after_mixed, metrics_mixed = three_updates(jax.jit(learner_for(mixed.replace(output_grad="compute")).update), state)
    for name, value in metrics.items():
        np.testing.assert_allclose(metrics_mixed[name], value, rtol=2e-3, err_msg=name)
    assert metrics_mixed != metrics  # it did compute in another precision
    assert all(x.dtype == jnp.float32 for x in jax.tree.leaves((after_mixed.params, after_mixed.opt_state))
               if jnp.issubdtype(x.dtype, jnp.floating))
    # Adam's first steps are about lr * sign(g): compare the gradients themselves
    full = one_batch(TINY)[1]
    for config in (mixed, mixed.replace(output_grad="compute")):
        grads = one_batch(config)[1]
        for group in state.params:
            assert relative(grads[group], full[group]) < 1e-2, (config.output_grad, group)


def _convolution_operands(jaxpr) -> list[tuple[str, str]]:
    """The operand dtypes of every convolution in the jaxpr (calls, custom rules and loop bodies entered)."""
    found = []
    for e in jaxpr.eqns:
        if e.primitive.name == "conv_general_dilated":
            found.append(tuple(str(v.aval.dtype) for v in e.invars))
        for j in _subjaxprs(e):
            found += _convolution_operands(j)
    return found


def test_output_grad_compute_keeps_the_forward_and_runs_every_convolution_gradient_in_bfloat16(state, one_batch):
    """output_grad "compute" with compute_dtype bfloat16: the loss is the same number (the forward pass is
    unchanged); the output layers' backward takes a bfloat16 cotangent, so no convolution of the gradient has a
    float32 operand (with "float32", the decoder's output layer's two gradients do); the gradient of one batch's loss
    differs from float32 cotangents' by less than 1e-2 (relative L2 per parameter group), as bfloat16 does from
    float32 (and so, against full float32, do the presets' gradients). With compute_dtype float32 (the switch back
    to full float32) it changes nothing, bit for bit."""
    def loss_grad_convolutions(config):
        loss, grads, jaxpr = one_batch(config)
        return loss, grads, _convolution_operands(jaxpr)

    mixed = TINY.replace(compute_dtype="bfloat16")
    (loss0, grads0, ops0), (loss1, grads1, ops1) = (loss_grad_convolutions(c)
                                                    for c in (mixed, mixed.replace(output_grad="compute")))
    assert loss1 == loss0
    before, after = ([o for o in ops if "float32" in o] for ops in (ops0, ops1))
    assert len(before) >= 2 and not after, (before, after)
    assert len(ops1) >= len(ops0)  # each in bfloat16 (the backward's vjp traces a forward XLA drops)
    for group in state.params:
        assert relative(grads1[group], grads0[group]) < 1e-2, group
    assert all(relative(grads1[group], grads0[group]) > 0 for group in ("encoder", "decoder"))
    presets = grads1  # bfloat16 with output_grad compute, as the task presets run
    (loss0, grads0, _), (loss1, grads1, _) = (loss_grad_convolutions(c)
                                              for c in (TINY, TINY.replace(output_grad="compute")))
    assert loss1 == loss0
    for a, b in zip(jax.tree.leaves(grads1), jax.tree.leaves(grads0)):
        np.testing.assert_array_equal(a, b)
    for group in state.params:  # the presets' arrangement against full float32: within bfloat16's rounding
        assert relative(presets[group], grads0[group]) < 1e-2, group


def _subjaxprs(eqn):
    for value in eqn.params.values():
        for v in value if isinstance(value, (tuple, list)) else (value,):
            if hasattr(v, "eqns") or hasattr(v, "jaxpr"):
                yield getattr(v, "jaxpr", v)


def _products_per_step(fn, *args) -> list[int]:
    """The matrix products in the body of each scan of fn(*args)'s jaxpr (scans inside calls and custom rules
    found too; calls inside a body entered), in the order they appear."""
    def products(jaxpr) -> int:
        return sum((e.primitive.name == "dot_general") + sum(products(j) for j in _subjaxprs(e)) for e in jaxpr.eqns)

    def scans(jaxpr) -> list[int]:
        found = []
        for e in jaxpr.eqns:
            if e.primitive.name == "scan":
                found.append(products(e.params["jaxpr"].jaxpr))
            else:
                for j in _subjaxprs(e):
                    found += scans(j)
        return found

    return scans(jax.make_jaxpr(fn)(*args).jaxpr)


def test_the_fused_core_computes_the_flax_cores_function_with_half_the_products_per_step(learner, state, update,
                                                                                        one_batch):
    """core_impl fused against flax (the default, the model of before): the filter's scan does 3 matrix products
    per step instead of 6 (forward and backward), the held-out imagination's 3 instead of 4 (the actions' share
    before its loop), the consistency term's k steps are unrolled, and the filter's outputs and gradients (random cotangents on all outputs), 3 updates' metrics and one
    batch's gradients agree to float32 rounding (1e-5 relative), the update's held-out scores and l_cc included."""
    assert TINY.core_impl == "flax"
    fused = learner_for(TINY.replace(core_impl="fused"))
    B, T, E = 2, 5, TINY.embed_dim
    embeds = jax.random.normal(jax.random.key(1), (T, B, E))
    actions = jax.random.normal(jax.random.key(2), (T, B, A))
    eps = jax.random.normal(jax.random.key(3), (T, B, TINY.latent))
    steps = [_products_per_step(lrn.model.filter, state.params, embeds, actions, eps) for lrn in (learner, fused)]
    assert steps == [[6], [3]], steps
    steps = [_products_per_step(lrn.model.imagine, state.params, embeds[0, :, :TINY.hidden] * 0, embeds[0, :, :TINY.hidden] * 0,
                                actions, eps) for lrn in (learner, fused)]
    assert steps == [[4], [3]], steps
    # the fused filter's own backward: every output's cotangent (random) to every input, against flax's autodiff;
    # its loop does 3 products per step too (the cotangents of z, of the output layer's input and of h)
    h0 = jax.random.normal(jax.random.key(5), (B, TINY.hidden))
    c0 = jax.random.normal(jax.random.key(6), (B, TINY.hidden))
    weights = jax.tree.map(lambda x: jax.random.normal(jax.random.key(7), x.shape),
                           jax.eval_shape(learner.model.filter, state.params, embeds, actions, eps))

    def scalar(lrn, *args):
        out = lrn.model.filter(args[0], *args[1:])
        return sum((x * wx).sum() for x, wx in zip(out, weights))

    def outputs(lrn, *args):  # the filter's outputs, the imagination's and the filter's gradients: one program a core
        params, embeds, actions, eps, h0, c0 = args
        return (lrn.model.filter(params, embeds, actions, eps), lrn.model.imagine(params, h0, c0, actions, eps),
                jax.grad(functools.partial(scalar, lrn), argnums=tuple(range(6)))(*args))

    args = (state.params, embeds, actions, eps, h0, c0)
    filtered, imagined, grads = zip(*(jax.jit(functools.partial(outputs, lrn))(*args) for lrn in (learner, fused)))
    for name, a, b in zip(filtered[0]._fields, *filtered):
        np.testing.assert_allclose(b, a, rtol=1e-5, atol=1e-6, err_msg=name)
    for name, a, b in zip("hcz", *imagined):
        np.testing.assert_allclose(b, a, rtol=1e-5, atol=1e-6, err_msg=name)
    assert relative(grads[1][0]["core"], grads[0][0]["core"]) < 1e-5
    for i, name in enumerate(("embeds", "actions", "eps", "h0", "c0"), start=1):
        np.testing.assert_allclose(grads[1][i], grads[0][i], rtol=1e-4, atol=1e-5, err_msg=name)
    assert _products_per_step(jax.grad(functools.partial(scalar, fused), argnums=(0, 1)), *args) == [3, 3]
    frames, actions = (jnp.swapaxes(x[:TINY.batch_size], 0, 1) for x in (state.data.frames, state.data.actions))
    cc_scans = [[e.params["unroll"] for e in jax.make_jaxpr(lrn.loss)(state.params, frames, actions, HP,
                                                                         jax.random.key(4)).jaxpr.eqns
                 if e.primitive.name == "scan" and e.params["length"] == TINY.horizon] for lrn in (learner, fused)]
    assert cc_scans == [[1], [TINY.horizon]], cc_scans  # the consistency term's k steps: unrolled when fused
    _, metrics = three_updates(update, state)
    _, metrics_fused = three_updates(jax.jit(fused.update), state)
    for name, value in metrics.items():
        np.testing.assert_allclose(metrics_fused[name], value, rtol=1e-5, err_msg=name)
    grads = [one_batch(lrn.config)[1] for lrn in (learner, fused)]
    for group in state.params:
        assert relative(grads[1][group], grads[0][group]) < 1e-5, group


def test_float32_layers_are_flax_layers_as_before_bit_for_bit():
    """The encoder and decoder at compute_dtype float32 and conv_impl grouped: the parameters, outputs and gradients
    of the flax layers the model was written with before (reference modules here), bit for bit."""
    import flax.linen as nn

    from cdjax.agents.pixel.networks import ConvDecoder, ConvEncoder, depth_to_space

    class Encoder(nn.Module):
        @nn.compact
        def __call__(self, x):
            for _ in range(2):
                x = nn.relu(nn.Conv(4, (4, 4), strides=(2, 2), padding="SAME")(x))
            return nn.Dense(16)(x.reshape(x.shape[0], -1))

    class Decoder(nn.Module):
        @nn.compact
        def __call__(self, x):
            y = nn.relu(nn.Dense(4 * 4 * 4)(x)).reshape(-1, 4, 4, 4)
            y = nn.relu(depth_to_space(nn.Conv(16, (3, 3), padding="SAME")(y)))
            y = depth_to_space(nn.Conv(24, (3, 3), padding="SAME")(y))
            return y[..., :3], nn.softplus(y[..., 3:]) + 0.01

    x = jax.random.uniform(jax.random.key(1), (3, 16, 16, 12))
    z = jax.random.normal(jax.random.key(2), (3, 20))
    for new, old, inp in [(ConvEncoder(2, 4, 16), Encoder(), x), (ConvDecoder(16, 2, 4, 0.01), Decoder(), z)]:
        params = new.init(jax.random.key(0), inp)
        old_params = old.init(jax.random.key(0), inp)
        assert jax.tree.structure(params) == jax.tree.structure(old_params)
        for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(old_params)):
            np.testing.assert_array_equal(a, b)
        out, vjp = jax.vjp(new.apply, params, inp)
        old_out, old_vjp = jax.vjp(old.apply, params, inp)
        cotangent = jax.tree.map(lambda o: jax.random.normal(jax.random.key(3), o.shape), out)
        for a, b in zip(jax.tree.leaves((out, vjp(cotangent))), jax.tree.leaves((old_out, old_vjp(cotangent)))):
            np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("impl", ["per-run", "matmul"])
@pytest.mark.parametrize("window,stride", [(4, 2), (3, 1)])
def test_conv_arrangements_equal_the_grouped_convolution_under_the_runs_vmap(impl, window, stride):
    """Each conv_impl computes lax.conv_general_dilated's value and both gradients under a vmap over runs with
    per-run kernels (float32, and bfloat16 operands returning float32)."""
    from jax import lax

    from cdjax.agents.pixel import convs

    fn = {"per-run": convs.per_run_conv, "matmul": convs.matmul_conv}[impl]
    R, N, S, C, F = 3, 2, 8, 5, 6  # runs, batch, size, input and output channels
    keys = jax.random.split(jax.random.key(window), 3)
    x = jax.random.normal(keys[0], (R, N, S, S, C))
    w = jax.random.normal(keys[1], (R, window, window, C, F))
    g = jax.random.normal(keys[2], (R, N, S // stride, S // stride, F))
    for conv, reference, exact in [(fn, lax.conv_general_dilated, True),
                                   (convs.operands_in(fn, jnp.bfloat16),
                                    convs.operands_in(lax.conv_general_dilated, jnp.bfloat16), False)]:
        def loss(x, w, g, conv=conv):
            y = conv(x, w, (stride, stride), "SAME", dimension_numbers=convs.NHWC)
            assert y.dtype == jnp.float32
            return (y * g).sum()

        got = jax.jit(jax.vmap(jax.value_and_grad(loss, (0, 1))))(x, w, g)
        want = jax.jit(jax.vmap(jax.value_and_grad(lambda x, w, g, ref=reference: loss(x, w, g, ref), (0, 1))))(x, w, g)
        for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(want)):
            if exact:  # float32: the same sums in another order
                np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-4)
            else:  # the input's gradient is bfloat16 (the operand's dtype): rounded to 8 bits either way
                assert relative(a, b) < 1e-2


# 32 channels: "auto" keeps the middle layers grouped and runs the narrow first (12 in) and last (24 out) per run
WIDE = TINY.replace(conv_channels=32)


@functools.lru_cache(maxsize=None)
def runs_update(impl: str):
    """(jit(vmap(update)) over 2 runs of WIDE in conv_impl `impl`, the runs' states (shapes), their HParams): the
    next two tests lower it and count its FLOPs from one trace (jit keeps it)."""
    learner = learner_for(WIDE.replace(conv_impl=impl))
    hps = jax.tree.map(lambda v: jnp.full((2,), v, jnp.float32), HP)
    states = jax.eval_shape(jax.vmap(learner.init), jax.random.split(jax.random.key(0), 2), hps)
    return jax.jit(jax.vmap(learner.update)), states, hps


def test_the_runs_vmap_gives_grouped_convolutions_only_with_conv_impl_grouped():
    """The lowered program of jit(vmap(update)) over 2 runs: grouped convolutions (feature_group_count 2) with
    'grouped'; ungrouped convolutions, two per layer use, with 'per-run'; batched matrix products and no
    convolution with 'matmul' (XLA then chooses how to run them; only a GPU measures which is faster); both kinds
    with 'auto', per layer."""
    import re

    counts = {}
    for impl in ("grouped", "per-run", "matmul", "auto"):
        update, states, hps = runs_update(impl)
        text = update.lower(states, hps).as_text()
        convolutions = re.findall(r"stablehlo\.convolution.*?feature_group_count = (\d+)", text)
        counts[impl] = (len(convolutions), {int(g) for g in convolutions},
                        len(re.findall(r"stablehlo\.dot_general.*?batching_dims = \[0\] x \[0\]", text)))
        if impl == "auto":  # grouped (2 groups) and ungrouped convolutions, counted apart
            counts["auto-split"] = (len([g for g in convolutions if g == "2"]), len([g for g in convolutions
                                                                                    if g == "1"]))
    grouped, per_run, matmul, auto = counts["grouped"], counts["per-run"], counts["matmul"], counts["auto"]
    assert grouped[0] > 0 and grouped[1] == {2}, grouped
    assert per_run[0] == 2 * grouped[0] and per_run[1] == {1}, per_run
    assert matmul[0] == 0 and matmul[2] > grouped[2], matmul
    # auto: some layer uses grouped, the others one convolution per run (two here), every use either
    in_groups, ungrouped = counts["auto-split"]
    assert auto[1] == {1, 2} and in_groups > 0 and ungrouped > 0, auto
    assert in_groups + ungrouped // 2 == grouped[0] and ungrouped % 2 == 0, counts["auto-split"]


def test_the_policys_rate_scales_only_the_policys_steps_and_zero_is_adam_at_lr():
    import optax

    from cdjax.agents.pixel.learner import optimizer

    keys = iter(jax.random.split(jax.random.key(5), 64))
    params = {g: {"w": jax.random.normal(next(keys), (3, 4)), "b": jax.random.normal(next(keys), (4,))}
              for g in ("encoder", "core", "policy")}
    hp = PixelHParams(lr=1e-3)
    before = optax.apply_if_finite(optax.chain(optax.clip(hp.clip), optax.adam(hp.lr)),
                                   max_consecutive_errors=1_000_000)
    opts = {"before": before, "zero": optimizer(hp), "policy": optimizer(hp.replace(lr_policy=4e-3))}
    states = {name: opt.init(params) for name, opt in opts.items()}
    assert jax.tree.structure(states["zero"]) == jax.tree.structure(states["before"])
    for step in range(3):
        grads = jax.tree.map(lambda p, step=step: 3 * jax.random.normal(jax.random.fold_in(next(keys), step), p.shape),
                             params)
        updates = {}
        for name, opt in opts.items():
            updates[name], states[name] = jax.jit(opt.update, compiler_options=EXACT)(grads, states[name], params)
        for a, b in zip(jax.tree.leaves(updates["zero"]), jax.tree.leaves(updates["before"])):
            np.testing.assert_array_equal(a, b)
        for group in params:
            scale = 4.0 if group == "policy" else 1.0
            for a, b in zip(jax.tree.leaves(updates["policy"][group]), jax.tree.leaves(updates["before"][group])):
                np.testing.assert_allclose(a, scale * b, rtol=1e-6)


def test_roofline_counts_each_product_and_convolution_and_scanned_bodies_times_their_length():
    """experiments.pixel.roofline's FLOPs (2 per multiply-add, as XLA counts them) on hand-counted programs: a
    convolution, its two gradients under the runs' vmap (the input's without the zeros a stride inserts), a product
    in a scan of 10 steps; the tiny model's update alike in every conv_impl; XLA's cost analysis counts that scan's
    body once, the roofline's figures are its counts over its own time."""
    from jax import lax

    from experiments.pixel import roofline

    R, N, S, C, F, K = 3, 2, 8, 5, 6, 4  # runs, batch, size, input and output channels, kernel window
    x, w, g = jnp.ones((R, N, S, S, C)), jnp.ones((R, K, K, C, F)), jnp.ones((R, N, S // 2, S // 2, F))
    forward = 2 * N * (S // 2) ** 2 * F * K * K * C  # stride 2, SAME: [N, S/2, S/2, F] outputs of K*K*C taps each

    def loss(x, w, g):
        return (lax.conv_general_dilated(x, w, (2, 2), "SAME", dimension_numbers=("NHWC", "HWIO", "NHWC")) * g).sum()

    def count(fn, *args):
        return roofline.matrix_flops(jax.make_jaxpr(fn)(*args).jaxpr)

    assert count(loss, x[0], w[0], g[0]) == (forward, 0)
    # grouped convolutions (feature_group_count R), the input's gradient from an input dilated 2x2
    assert count(jax.vmap(jax.value_and_grad(loss, (0, 1))), x, w, g) == (3 * R * forward, 0)
    m = jnp.ones((F, F))

    def scanned(y):
        return lax.scan(lambda c, _: (c @ m, None), y, None, length=10)[0]

    y = jnp.ones((16, F))
    step = 2 * 16 * F * F
    assert count(lambda y: lax.cond(y[0, 0] > 0, scanned, lambda y: y @ m, y), y) == (10 * step, 0)
    assert count(lambda y: lax.while_loop(lambda c: c[0, 0] < 5, lambda c: c @ m, y), y) == (step, 1)
    # the model's FLOPs do not depend on how its convolutions are arranged (per-run's custom rule also computes the
    # frames' gradient, dead code that XLA drops and the count must too)
    counts = {roofline.program_flops(*runs_update(impl)) for impl in ("grouped", "per-run", "matmul")}
    assert len(counts) == 1 and min(counts)[0] > 0, counts
    row = roofline.roofline(scanned, (y,), frames=16, peak=1.0, repeats=1)
    assert row["flops_per_frame"] == 10 * step / 16 and row["while_loops_counted_once"] == 0
    assert row["xla_flops_per_frame"] < 2 * step / 16  # XLA: the body once (and a few elementwise flops)
    assert row["achieved_tflops"] == pytest.approx(10 * step / row["update_s"] / 1e12)
    assert row["of_peak"] == pytest.approx(row["achieved_tflops"]) and row["frames_per_s"] == pytest.approx(
        16 / row["update_s"])
