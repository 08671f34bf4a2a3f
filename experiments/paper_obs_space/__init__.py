"""The paper's observation-space setting (Sodhani et al., 2019, section 5.1), powered: Mb-Mf vs Mb-Mf + consistency.

Tasks ant, humanoid, half-cheetah, swimmer; per task the arms model-free, Mb-Mf (alpha = 0, after the model-based
phase of Nagabandi et al.), CD k=5 and CD k=20 with the paper's weights (both paths of l_cc at alpha:
cc_model = cc_policy = 1) and CD k=20 at cdjax's defaults (cc_policy = 0.1), 10 seeds vmapped per arm; and on ant and
half-cheetah the consistency schedule of the presets (the first epoch only) against the paper's (every minibatch of
every epoch). The experiment runs as UNITS, each one `cdjax sweep` (a unit may hold several, one after another) that finishes on one
GPU within one device lease (PLAN.md):

    python -m experiments.paper_obs_space list                           # the units, their budgets and estimates
    python -m experiments.paper_obs_space run ant-1 --out DIR             # one unit (its sweeps under DIR/)
    python -m experiments.launch start paper_obs_space ant-1 --work DIR  # the same detached (poll, collect)
    python -m experiments.paper_obs_space keep runs/units-back/ant-1      # what came back -> data/ant-1/
    python -m experiments.paper_obs_space report                          # RESULTS.md from the kept data (data/)
    python -m experiments.paper_obs_space.phase_check --task halfcheetah  # the Mb-Mf phase's variants side by side
    python -m experiments.paper_obs_space.yardstick                       # the yardstick files (collected once)

A unit runs `cdjax sweep --preset paper-<task>` (cdjax/agents/obs/presets.py holds every setting) with the unit's
arms, grid and budget, the task's yardstick (yardstick/<task>.npz) and a record of the machine; any further
`cdjax sweep` option passes through (e.g. `--steps`, `--seeds` for a smaller try); `train --task TASK` runs the
task's preset as it stands, in one sweep.
"""

from __future__ import annotations

import dataclasses

TASKS = ("ant", "humanoid", "halfcheetah", "swimmer")
# Arm keys of the report: (arm name in the sweep, what tells them apart) -> ARMS; see report.arm_key.
ARMS = ("model-free", "mbmf", "cd-k5", "cd-k20-paper", "cd-k20", "cd-k20-paper-schedule", "mbmf-value0",
        "mbmf-model-only")
START_TASKS = ("halfcheetah",)  # why the Mb-Mf start learns slower there: the hand-over's parts ablated (unit -5)
ABLATION_TASKS = ("ant", "humanoid")  # the paper's k ablation (with the model-free arm)
SCHEDULE_TASKS = ("ant", "halfcheetah")  # the consistency schedule, the presets' against the paper's

# The paper's CD: both paths of the consistency gradient at alpha (cdjax's default is cc_policy = 0.1).
PAPER_WEIGHTS = ("--cc-policy", "1")
# The paper's schedule: the consistency term in every minibatch of every epoch, on every window (the presets: the
# first epoch only; with sequences of 20 steps and k = 20 there is one window per sequence either way).
PAPER_SCHEDULE = ("--cc-epochs", "0", "--cc-windows", "0")
# The confirmation units' base seed (every other unit runs base seed 0: `cdjax sweep --seed`).
CONFIRM_SEED = 1


@dataclasses.dataclass(frozen=True)
class Part:
    """One `cdjax sweep` of a unit: arms of one task at its budget, with more options."""

    name: str  # the run directory's name under the unit's directory
    arms: tuple[str, ...]
    options: tuple[str, ...] = ()  # more `cdjax sweep` options (a grid, a schedule)
    seeds: int = 10
    runs_per_arm: int = 1  # hyper-parameter combinations per arm (a grid of 2 doubles the runs)
    rate_factor: float = 1.0  # its rate relative to the task's (the paper's schedule computes l_cc 4x as often)

    @property
    def runs(self) -> int:
        return len(self.arms) * self.runs_per_arm * self.seeds

    @property
    def phased(self) -> int:
        """Arms that run the Mb-Mf phase (every arm with a model; each runs it once, vmapped over its runs)."""
        return sum(a != "model-free" for a in self.arms)


@dataclasses.dataclass(frozen=True)
class Task:
    """A task's budget and what its time estimates rest on (aggregate env steps/s of ~20 vmapped runs on one H200)."""

    name: str
    steps: int  # env steps per run, the Mb-Mf phase's included
    rate: float  # aggregate training env steps/s on one H200, PPO + model (+ l_cc on the presets' schedule)
    rate_source: str  # where `rate` comes from
    phase_s: float  # estimated seconds of one arm's Mb-Mf phase, 10 runs vmapped (20 runs: PHASE_20_RUNS x that)
    provisional: bool = False  # rate not measured at these settings: the budget waits for the first unit's rate


# An arm of 20 runs (two weights x 10 seeds) runs its phase for all 20 at once: latency-bound, with twice the MPC
# candidates per step: the ratio of ant's measured phase at 20 runs to its phase at 10 (PLAN.md, the units' table).
PHASE_20_RUNS = 1.8
# Rates and phases: what each task's units 1 and 3 measured on one H200 (PLAN.md, the units' table, has every figure).
TASK_BUDGETS = {
    "ant": Task("ant", 50_000_000, 1.6e6, "units ant-1..3 (PLAN.md)", phase_s=40),  # MPC horizon 5
    "halfcheetah": Task("halfcheetah", 10_000_000, 0.37e6, "units halfcheetah-1 and -3 (PLAN.md)",
                        phase_s=88),  # MPC horizon 20
    "humanoid": Task("humanoid", 10_000_000, 0.5e6, "units humanoid-1 and -3 (PLAN.md)", phase_s=80),  # horizon 5
    "swimmer": Task("swimmer", 5_000_000, 0.24e6, "units swimmer-1 and -3 (PLAN.md)", phase_s=92),  # horizon 20
}


@dataclasses.dataclass(frozen=True)
class Unit:
    """What one device lease runs: one or two sweeps of one task, one after the other."""

    name: str
    task: str
    parts: tuple[Part, ...]
    note: str = ""

    @property
    def budget(self) -> Task:
        return TASK_BUDGETS[self.task]

    def estimate(self, compile_s: float = 180.0, eval_s: float = 60.0) -> dict:
        """Estimated seconds per part and in all, on one H200: compile + phases + training + final evaluation."""
        t = self.budget
        parts = {}
        for p in self.parts:
            train = p.runs * t.steps / (t.rate * p.rate_factor)
            phase = p.phased * t.phase_s * (PHASE_20_RUNS if p.runs_per_arm > 1 else 1.0)
            parts[p.name] = {"compile": compile_s, "phase": phase, "train": train, "eval": eval_s,
                             "total": compile_s + phase + train + eval_s}
        return {"parts": parts, "total": sum(v["total"] for v in parts.values())}


def _units() -> dict[str, Unit]:
    mf_mbmf = Part("mf-mbmf", ("model-free", "mbmf"))
    cd20 = Part("cd-k20", ("cd-k20",), ("--cc-policy", "1", "0.1"), runs_per_arm=2)  # paper weights and defaults
    # 4 of a 20-step sequence's 16 windows (the base config's horizon too: it is validated before the arm sets it)
    cd5 = Part("cd-k5", ("cd-k5",), PAPER_WEIGHTS + ("--cc-windows", "4", "--horizon", "5"))
    # CD k=20 at cdjax's weights on the paper's schedule: against cd-k20's cdjax-weights runs (the same seeds)
    schedule = Part("schedule", ("cd-k20",), PAPER_SCHEDULE, rate_factor=0.7)
    # Mb-Mf with parts of the hand-over left out, 5 seeds each (fewer runs train slower in aggregate: ~0.6x):
    # the value not fitted to the DAgger returns; PPO from the untrained policy and value (the phase's model and
    # normalisation only). Against mbmf (the distilled policy and fitted value) and model-free (nothing).
    value0 = Part("value0", ("mbmf",), ("--phase-value-epochs", "0"), seeds=5, rate_factor=0.6)
    model_only = Part("model-only", ("mbmf",), ("--phase-hand-policy", "false", "--phase-value-epochs", "0"), seeds=5,
                      rate_factor=0.6)
    # The replication of the x0.1 rerun's one pooled finding (P(CD k=20 at cdjax's weights > Mb-Mf) = 0.698 [0.57,
    # 0.815] across the four tasks, head-0.1/): the same two arms on 10 fresh seeds (base seed 1: keys that no other
    # unit used), kept apart in confirm/ (PLAN.md says what it tests and how it is read).
    confirm = Part("confirm", ("mbmf", "cd-k20"), ("--seed", str(CONFIRM_SEED)))
    units = {}
    for task in TASKS:
        units[f"{task}-1"] = Unit(f"{task}-1", task, (mf_mbmf,), "model-free and Mb-Mf")
        units[f"{task}-2"] = Unit(f"{task}-2", task, (cd20,), "CD k=20, the paper's weights and cdjax's")
        units[f"{task}-3"] = Unit(f"{task}-3", task, (cd5,), "CD k=5, the paper's weights")
        if task in SCHEDULE_TASKS:
            units[f"{task}-4"] = Unit(f"{task}-4", task, (schedule,), "CD k=20, cdjax's weights, the paper's schedule")
        if task in START_TASKS:
            units[f"{task}-5"] = Unit(f"{task}-5", task, (value0, model_only),
                                      "Mb-Mf's hand-over ablated: the value not fitted; the model only")
        units[f"{task}-6"] = Unit(f"{task}-6", task, (confirm,),
                                  f"Mb-Mf and CD k=20 at cdjax's weights on fresh seeds (base seed {CONFIRM_SEED})")
    return units


UNITS = _units()
