"""The consistency term's two path weights on GPU: a vmapped (cc_model x cc_policy) grid per task."""

TASKS = ("ant", "halfcheetah")
