"""cdjax: consistent dynamics models (Sodhani et al., 2019) as one jitted JAX pipeline on MuJoCo-MJX.

The package's face is the observation-space agent (`cdjax.agents.obs`), the paper's main setting:

    from cdjax import Config, HParams, make_train
    train = make_train(Config(env="ant"))          # train(key, hp) -> (state, metrics); jit/vmap it yourself

`make_agent(config)` gives that agent's pieces (init, update, collect, loss, act, model_step, ...);
`make_trainer(config)` gives it as every setting gives itself to the host side (`cdjax.protocol.Trainer`).
"""

from cdjax.runtime import apply_xla_defaults

apply_xla_defaults()  # before anything starts a JAX backend


import contextlib as _contextlib
import io as _io

# mujoco.mjx prints to stdout when its optional warp backend is missing; keep `import cdjax` quiet.
with _contextlib.redirect_stdout(_io.StringIO()):
    from cdjax.agents.obs import (Config, HParams, MbMfPhase, ObsAgent, TrainState, make_agent, make_mbmf_phase,
                                  make_train, make_trainer, stack_hparams, total_env_steps)
    from cdjax.protocol import ConfigError, Trainer

__all__ = ["Config", "ConfigError", "HParams", "MbMfPhase", "ObsAgent", "TrainState", "Trainer", "make_agent",
           "make_mbmf_phase", "make_train", "make_trainer", "stack_hparams", "total_env_steps"]
__version__ = "0.1.0"
