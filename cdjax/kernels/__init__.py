"""Hand-written kernels (Pallas) for parts of the update that XLA runs as many small kernels.

`chain`: the consistency term's fused k-step chain (`cdjax.consistency.fused_chain`) as one kernel launch for its
forward and one for its backward.
"""
