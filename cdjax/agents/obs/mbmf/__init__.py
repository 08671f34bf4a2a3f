"""The model-based phase of Mb-Mf (Nagabandi et al., 2017): its sizes (`spec`) and its program (`phase`)."""

from cdjax.agents.obs.mbmf.data import model_objective
from cdjax.agents.obs.mbmf.phase import make_mbmf_phase, make_mpc_controller
from cdjax.agents.obs.mbmf.spec import MbMfPhase, total_env_steps, validate_phase
from cdjax.replay import RingBuffer, fit

__all__ = ["MbMfPhase", "RingBuffer", "fit", "make_mbmf_phase", "make_mpc_controller", "model_objective",
           "total_env_steps", "validate_phase"]
