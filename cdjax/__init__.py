"""cdjax: consistent dynamics models (Sodhani et al., 2019) as one jitted JAX pipeline on MuJoCo-MJX."""

from cdjax.config import Config, ConfigError, HParams
from cdjax.mbmf import MbMfPhase, make_mbmf_phase, total_env_steps
from cdjax.train import TrainState, Trainer, make_train, make_trainer

__all__ = ["Config", "ConfigError", "HParams", "MbMfPhase", "TrainState", "Trainer", "make_mbmf_phase", "make_train",
           "make_trainer", "total_env_steps"]
__version__ = "0.1.0"
