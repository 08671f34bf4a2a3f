"""cdjax: consistent dynamics models (Sodhani et al., 2019) as one jitted JAX pipeline on MuJoCo-MJX."""

from cdjax.runtime import apply_cpu_workaround

apply_cpu_workaround()  # before anything starts a JAX backend


import contextlib as _contextlib
import io as _io

# mujoco.mjx prints to stdout when its optional warp backend is missing; keep `import cdjax` quiet.
with _contextlib.redirect_stdout(_io.StringIO()):
    from cdjax.config import Config, ConfigError, HParams
    from cdjax.mbmf import MbMfPhase, make_mbmf_phase, total_env_steps
    from cdjax.train import TrainState, Trainer, make_train, make_trainer

__all__ = ["Config", "ConfigError", "HParams", "MbMfPhase", "TrainState", "Trainer", "make_mbmf_phase", "make_train",
           "make_trainer", "total_env_steps"]
__version__ = "0.1.0"
