"""cdjax: consistent dynamics models (Sodhani et al., 2019) as one jitted JAX pipeline on MuJoCo-MJX."""

from cdjax.config import Config, ConfigError, HParams
from cdjax.train import TrainState, Trainer, make_train, make_trainer

__all__ = ["Config", "ConfigError", "HParams", "TrainState", "Trainer", "make_train", "make_trainer"]
__version__ = "0.1.0"
